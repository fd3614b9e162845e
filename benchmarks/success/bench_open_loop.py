"""Open-loop action error of trained runs: every run's policy samples chunks for the same
demonstration windows, and the steps it would execute are compared with the demonstrator's.

A closed-loop success of 0 says a policy failed, not why. This asks the narrower question whether
the network reproduces the demonstrations it was trained on: for each run of a ``bench_success``
grid (its ``best.pt``, EMA weights) and the same ``--windows`` windows of the run's own dataset
(seeded, identical across runs of a task), the executed steps [To-1, To-1+K) of one sampled chunk
(seeded noise) against the demonstrated ones, in the policy's normalised action units (each action
dimension mapped to [-1, 1]) so that dimensions weigh alike; padded steps are left out. DDPM runs are
also read under DDIM-16, the re-scoring the success tables carry.

    python -m benchmarks.success.bench_open_loop --root runs/bench_success_stackcube \\
        --task maniskill_stackcube --policies l1flow flow ddpm regression --seeds 0 1 2

Reported per run and per method (mean and spread over seeds): ``l1`` (mean absolute error per
executed action entry) and ``l1_per_dim``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

from benchmarks.lib.common import format_table, machine_info, parse_args, save_results
from l1flow_rl.modules.actor import L1FlowActor

#: extra samplers read from the same checkpoint: method -> (label, sampler name, kwargs)
RESCORED = {"ddpm": ("ddpm_ddim16", "ddim", {"steps": 16})}


def demonstration_windows(cfg: Any, count: int, seed: int) -> TensorDictBase:
    """``count`` windows of the run's dataset, drawn by its chunk buffer with a fixed seed (the same
    windows for every run trained on the same file with the same horizons)."""
    from omegaconf import OmegaConf

    from l1flow_rl.config import TaskConfig
    from l1flow_rl.workspace.dataset import load_task_episodes, make_train_buffer, resolve_dataset

    cfg = cfg.copy()
    cfg.task = OmegaConf.merge(OmegaConf.structured(TaskConfig), cfg.task)  # typed, as the train job has it
    episodes = load_task_episodes(cfg, resolve_dataset(cfg))
    buffer = make_train_buffer(cfg, episodes, seed=seed)
    batches, have = [], 0
    while have < count:
        batch = buffer.sample()
        batches.append(batch)
        have += batch.shape[0]
    return torch.cat(batches)[:count]


def open_loop_error(actor: L1FlowActor, windows: TensorDictBase, seed: int) -> dict[str, Any]:
    """Executed steps of one sampled chunk per window against the demonstrated ones (normalised)."""
    policy = actor.policy
    with torch.no_grad():
        chunk = policy.sample_chunk(windows["observation"], generator=torch.Generator().manual_seed(seed))
        norm = policy.action_normalizer.normalize
        err = (norm(policy.executable(chunk)) - norm(policy.executable(windows["action_chunk"]))).abs()
    valid = torch.ones(err.shape[:-1], dtype=torch.bool)
    if "action_is_pad" in windows:
        valid = ~policy.executable(windows["action_is_pad"].unsqueeze(-1)).squeeze(-1).bool()
    kept = err[valid]  # [M, A]: executed entries that are real demonstrated actions
    if kept.numel() == 0:
        raise ValueError("every executed step of the chosen windows is padding; draw more windows")
    return {
        "l1": round(float(kept.mean()), 5),
        "l1_per_dim": [round(float(v), 5) for v in kept.mean(0)],
        "steps_compared": int(kept.shape[0]),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    from l1flow_rl.workspace.checkpoint import load_actor

    torch.set_num_threads(args.threads)
    figures: dict[str, Any] = {
        "machine": machine_info("cpu"),
        "quick": args.quick,
        "task": args.task,
        "root": str(args.root),
        "windows": args.windows,
        "window_seed": args.window_seed,
        "runs": {},
        "missing": [],
    }
    windows: dict[str, TensorDictBase] = {}  # per dataset file
    for method in args.policies:
        for seed in args.seeds:
            ckpt = Path(args.root) / args.task / method / f"seed{seed}" / "checkpoints" / "best.pt"
            if not ckpt.is_file():
                figures["missing"].append(str(ckpt))
                continue
            actor, cfg = load_actor(ckpt)
            key = f"{cfg.data_dir}|{cfg.demos.num}|{cfg.policy.obs_horizon}|{cfg.policy.pred_horizon}"
            if key not in windows:
                windows[key] = demonstration_windows(cfg, args.windows, args.window_seed)
            arms = {method: actor}
            if method in RESCORED:
                label, name, kwargs = RESCORED[method]
                arms[label] = actor.with_sampler(name, **kwargs)
            for label, arm in arms.items():
                result = open_loop_error(arm, windows[key], seed=args.noise_seed)
                figures["runs"].setdefault(label, {})[f"seed{seed}"] = result
                print(f"{label:>12} seed {seed}: l1 {result['l1']:.4f}", flush=True)
    figures["methods"] = {
        label: {
            "l1_mean": round(statistics.mean(r["l1"] for r in runs.values()), 5),
            "l1_std": round(statistics.stdev(r["l1"] for r in runs.values()), 5) if len(runs) > 1 else 0.0,
            "seeds": len(runs),
        }
        for label, runs in figures["runs"].items()
    }
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--root", required=True, help="a bench_success root (runs/<root>/<task>/<method>/seedN)"
    )
    parser.add_argument("--task", required=True)
    parser.add_argument("--policies", nargs="+", default=["l1flow", "flow", "ddpm", "regression"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--windows", type=int, default=256)
    parser.add_argument("--window-seed", type=int, default=12345)
    parser.add_argument("--noise-seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None, help="default: benchmarks/results/open_loop_<task>.json")
    parser.add_argument("--quick", action="store_true", help="marks the file as a script check")
    args = parse_args(parser, argv)
    figures = run(args)
    if not figures["runs"]:
        print(f"no checkpoints found under {args.root}/{args.task}: " + ", ".join(figures["missing"]))
        return 1
    out = args.out or f"benchmarks/results/open_loop_{args.task}.json"
    save_results(out, figures)
    rows = [{"method": k, **v} for k, v in figures["methods"].items()]
    print(format_table(rows, ["method", "l1_mean", "l1_std", "seeds"]))
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
