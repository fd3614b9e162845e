"""Why an FQL run's one-step actor mu fails where its BC flow succeeds: is mu not yet a distillation of
the flow, or has it climbed the critics away from the demonstrations?

For each FQL fine-tuning checkpoint (``checkpoints/latest.pt`` or a copy of it), the run's loss is
rebuilt from its BC start and loaded, and on ``--batches`` batches of demonstration windows (the
offline buffer, as the run samples it) the executed steps [h, A] (normalised units) are compared:

* ``mu_vs_teacher``: |mu(s, z) - flow(s, z)|, the same noise z (what distillation drives to 0);
* ``teacher_spread``: |flow(s, z) - flow(s, z')|, two noises: the flow's own spread, the scale at which
  mu's error stops mattering;
* ``mu_vs_demo`` and ``teacher_vs_demo``: against the demonstrated chunk;
* ``q_mu``, ``q_teacher``, ``q_demo``: the online critics' mean value of each (FQL acts with mu, so
  ``q_mu`` above ``q_teacher`` with ``mu_vs_teacher`` above ``teacher_spread`` reads "climbed the
  critics off the flow").
* ``mu_spread``: |mu(s, z) - mu(s, z')|: how much of mu's gap is its answer to the noise (the flow
  nearly ignores it: ``teacher_spread``), not a wrong mean.
* ``grad_q_over_distill`` and ``grad_cosine``: at mu's chunk, the actor loss's two gradients over
  the executed steps (``lambda * Q`` against ``alpha * distillation``): their norms' ratio and cosine.
  A ratio near 1 with cosine near -1 reads "mu sits where the critics' pull balances distillation":
  more updates will not close its gap to the flow, only alpha can; a small ratio reads "mu is still
  being fitted": the gap is a matter of updates.
* ``validation``: the run's validation success at the checkpoint's update count, where it ran one.

All are means of absolute differences over the executed steps, actions and windows.

    .venv/bin/python -m benchmarks.diagnose_fql \\
        --run runs/bench_ft_can_mixed30c_fql/robosuite_can_fql_offline_seed0 \\
        --checkpoints runs/fql_snap/*.pt --out benchmarks/results/fql_distill_can_mixed30c.json
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

import torch

from benchmarks.bench_critic_bias import load_run
from benchmarks.common import machine_info, save_results
from l1flow_rl.objectives.finetune_registry import FINETUNE_ALGORITHMS
from l1flow_rl.workspace.checkpoint import load_checkpoint
from l1flow_rl.workspace.rl_data import RLBuffers

__all__ = ["compare", "main", "validations"]


@torch.no_grad()
def compare(loss, batch) -> dict[str, float]:
    """The measures above on one batch of windows (see the module's docstring)."""
    obs = loss.read_observation(batch, loss.tensor_keys.observation)
    flow, n = loss.reader, obs.shape[0]
    z, z2 = loss._noise(n, flow.action_normalizer.scale), loss._noise(n, flow.action_normalizer.scale)
    with loss.actor_network_params.to_module(loss.actor_network):
        mu = loss.mu.chunk(obs, z)
        mu2 = loss.mu.chunk(obs, z2)
    t1, t2 = loss.teacher_chunk(obs, z), loss.teacher_chunk(obs, z2)
    demo = flow.action_normalizer.normalize(batch.get(loss.tensor_keys.action_chunk).reshape(t1.shape))
    ex = loss.executed

    def gap(a, b):
        return float((ex(a) - ex(b)).abs().mean())

    def value(x):
        return float(loss.aggregate(loss.q(obs, flow.action_normalizer.unnormalize(ex(x)))).mean())

    with torch.enable_grad():  # the actor loss's two gradients at mu's chunk, as FQLLoss.actor_loss forms it
        x = mu.detach().requires_grad_(True)
        distill, q, lam = loss.actor_terms(obs, x, t1)
        (g_distill,) = torch.autograd.grad(loss.alpha * distill, x)
        (g_q,) = torch.autograd.grad(-lam * q.mean(), x)
    g_distill, g_q = ex(g_distill).flatten(), ex(g_q).flatten()
    return {
        "mu_vs_teacher": gap(mu, t1),
        "teacher_spread": gap(t1, t2),
        "mu_spread": gap(mu, mu2),
        "mu_vs_demo": gap(mu, demo),
        "teacher_vs_demo": gap(t1, demo),
        "q_mu": value(mu),
        "q_teacher": value(t1),
        "q_demo": value(demo),
        "grad_q_over_distill": float(g_q.norm() / g_distill.norm().clamp_min(1e-12)),
        "grad_cosine": float(torch.nn.functional.cosine_similarity(g_q, g_distill, dim=0)),
    }


def validations(run: Path) -> dict[int, float]:
    """The run's validation success_once by step (offline updates, then env steps): ``history.json``
    (written when a run ends), overlaid by the csv logger's live file, which a stopped or running run
    keeps up to date."""
    history = run / "history.json"
    evals = json.loads(history.read_text())["evals"] if history.is_file() else []
    found = {e["step"]: e["success_once"] for e in evals if e["split"] == "val"}
    live = run / "logs" / "finetune" / "scalars" / "val" / "success_once.csv"
    if live.is_file():
        for line in live.read_text().splitlines():
            step, value = line.split(",")
            found[int(step)] = float(value)
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--run", required=True, help="the FQL run (its config.yaml, BC start and demonstrations)"
    )
    parser.add_argument(
        "--checkpoints", nargs="*", default=[], help="default: the run's checkpoints/latest.pt"
    )
    parser.add_argument("--batches", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    run = Path(args.run)
    cfg, bc_actor, episodes = load_run(run)
    if cfg.finetune.algorithm != "fql":
        parser.error(f"--run {run}: finetune.algorithm is {cfg.finetune.algorithm!r}, expected 'fql'")
    paths = [Path(p) for p in args.checkpoints] or [run / "checkpoints" / "latest.pt"]
    rows = []
    for path in paths:
        state = load_checkpoint(path)
        if "loss" not in state:
            parser.error(f"--checkpoints {path}: no 'loss' entry (a fine-tuning latest.pt holds one)")
        loss = FINETUNE_ALGORITHMS["fql"].build(copy.deepcopy(bc_actor), cfg.finetune)
        loss.load_state_dict(state["loss"])
        loss.eval()
        torch.manual_seed(args.seed)
        buffers = RLBuffers(cfg, episodes, loss.rl_horizon, seed=args.seed)
        batches = [compare(loss, buffers.sample_offline()) for _ in range(args.batches)]
        row = {k: round(sum(b[k] for b in batches) / len(batches), 5) for k in batches[0]}
        progress = state["progress"]
        row = {
            "checkpoint": str(path),
            "step": progress["offline_updates"] + progress["env_steps"],
            "updates": progress["offline_updates"] + progress["online_updates"],
            "env_steps": progress["env_steps"],
            **row,
        }
        rows.append(row)
        print(row, flush=True)
    rows.sort(key=lambda r: (r["updates"], r["env_steps"]))
    validated = validations(run)
    for row in rows:
        row["validation"] = validated.get(row["step"])
    save_results(
        Path(args.out),
        {
            "run": str(run),
            "task": str(cfg.task.name),
            "alpha": float(cfg.finetune.fql.alpha),
            "normalize_q_loss": bool(cfg.finetune.fql.normalize_q_loss),
            "batches": args.batches,
            "batch_size": int(cfg.finetune.batch_size),
            "machine": machine_info("cpu"),
            "rows": rows,
        },
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
