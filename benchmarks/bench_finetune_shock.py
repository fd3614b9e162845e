"""What the first fine-tuning updates do to a converged BC flow's fit, under each optimiser start.

    .venv/bin/python -m benchmarks.bench_finetune_shock --checkpoint runs/bc/checkpoints/best.pt \\
        --task robosuite_can --updates 1155 --out benchmarks/results/finetune_shock_robosuite_can.json

Every constant-LR fine-tuning arm (filtered BC and continued BC alike) validated 0.1-0.2 below its
start within ~1k updates and climbed back later; the continued-BC run's own batch loss went from the BC
run's last ~0.022 to ~0.035-0.045 within its first 50 updates. This script asks which optimiser start
causes that, with no env step: from the checkpoint's (EMA) weights, the same batches of the BC run's
demonstrations (filtered BC's offline phase: the successful episodes) train one copy of the flow per
arm, and the L1 Flow loss on a fixed held set of batches (fixed t and noise) is read at fixed update
counts. Arms:

- ``fresh_adam``: what ``l1flow-rl finetune`` does (Adam at ``finetune.lr`` from zero moments);
- ``restored_adamw``: the BC run's own AdamW (betas 0.95/0.999, wd 1e-6) with its saved moments, at
  the same LR;
- ``warmup``: fresh Adam with a linear LR warm-up over ``--warmup`` updates (the BC run's 200);
- ``low_lr``: fresh Adam at ``--low-lr`` (a third of the BC run's peak);
- ``fresh_adam_ema``: ``fresh_adam``'s updates, read on their Diffusion-Policy EMA (power 0.75, what
  ``finetune.ema_power=0.75`` acts with), its counter from 0 (its first updates copy the raw weights);
- ``fresh_adam_bc_ema``: the same, the EMA continuing the BC run's (its counter from the checkpoint's
  ``ema_n_averaged``, as if BC had gone on).
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import torch

from benchmarks.common import machine_info, save_results
from l1flow_rl.commands.cli import compose_config
from l1flow_rl.modules.ema import make_ema
from l1flow_rl.objectives.finetune_registry import FINETUNE_ALGORITHMS
from l1flow_rl.workspace.checkpoint import load_actor, load_checkpoint
from l1flow_rl.workspace.dataset import load_task_episodes
from l1flow_rl.workspace.finetune import adopt_start_data, start_dataset
from l1flow_rl.workspace.rl_data import RLBuffers

ARMS = ("fresh_adam", "restored_adamw", "warmup", "low_lr", "fresh_adam_ema", "fresh_adam_bc_ema")


def make_optimizer(arm: str, params: list, bc_state: dict, args):
    """The arm's optimiser and LR schedule (a LambdaLR multiplier, or None)."""
    if arm == "restored_adamw":
        tcfg = bc_state["config"]["train"]
        opt = torch.optim.AdamW(
            params, lr=args.lr, betas=tuple(tcfg["betas"]), weight_decay=tcfg["weight_decay"]
        )
        saved = bc_state["optimizer"]
        if len(saved["param_groups"][0]["params"]) != len(params):
            n_saved = len(saved["param_groups"][0]["params"])
            raise ValueError(f"the BC optimiser holds {n_saved} parameters, the flow {len(params)}")
        opt.load_state_dict(saved)
        for group in opt.param_groups:  # the saved LR is the cosine schedule's last (~0)
            group["lr"] = args.lr
        return opt, None
    lr = args.low_lr if arm == "low_lr" else args.lr  # fresh_adam(_ema), warmup
    opt = torch.optim.Adam(params, lr=lr)
    if arm == "warmup":
        return opt, torch.optim.lr_scheduler.LambdaLR(opt, lambda n: min(1.0, (n + 1) / args.warmup))
    return opt, None


def held_loss(loss, batches: list) -> float:
    """The L1 Flow loss on the held batches with t and noise fixed by the seed (the same for every arm
    and read)."""
    torch.manual_seed(12345)
    with torch.no_grad():
        return float(torch.stack([loss(b)["loss_bc"] for b in batches]).mean())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--task", default="robosuite_can")
    parser.add_argument("--arms", nargs="+", default=list(ARMS), choices=ARMS)
    parser.add_argument("--updates", type=int, default=1155)
    parser.add_argument("--reads", nargs="+", type=int, default=[10, 25, 50, 100, 200, 400, 700, 1155])
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--low-lr", type=float, default=1e-4)
    parser.add_argument("--warmup", type=int, default=200)
    parser.add_argument("--held-batches", type=int, default=16)
    parser.add_argument("--out", required=True)
    parser.add_argument(
        "--add", action="store_true", help="keep the arms --out holds (same checkpoint and settings)"
    )
    args = parser.parse_args(argv)

    cfg = compose_config(
        ["finetune=filtered_bc", f"checkpoint={args.checkpoint}", f"task={args.task}"], command="finetune"
    )
    bc_state = load_checkpoint(args.checkpoint)
    start, bc_cfg = load_actor(args.checkpoint, use_ema=True)
    adopt_start_data(cfg, bc_cfg, given=[])
    episodes = load_task_episodes(cfg, start_dataset(cfg, bc_state, given=[]))
    algorithm = FINETUNE_ALGORITHMS["filtered_bc"]
    horizon = algorithm.build(copy.deepcopy(start), cfg.finetune).rl_horizon

    def buffers(seed: int) -> RLBuffers:
        return RLBuffers(cfg, episodes, horizon, seed=seed, successful_episodes_only=True)

    held_from = buffers(seed=999)
    held = [held_from.sample_offline() for _ in range(args.held_batches)]
    settings = {
        "checkpoint": args.checkpoint,
        "task": args.task,
        "batch_size": int(cfg.finetune.batch_size),
        "lr": args.lr,
        "low_lr": args.low_lr,
        "warmup": args.warmup,
        "reads": [0, *args.reads],
    }
    results = {}
    if args.add and Path(args.out).is_file():
        saved = json.loads(Path(args.out).read_text())
        differ = [k for k, v in settings.items() if saved.get(k) != v]
        if differ:
            parser.error(f"--add: {args.out} was measured with other {differ}; measure into a new --out")
        results = saved["arms"]
    for arm in args.arms:
        torch.manual_seed(0)
        loss = algorithm.build(copy.deepcopy(start), cfg.finetune)
        params = [p for p in loss.actor.parameters() if p.requires_grad]
        opt, sched = make_optimizer(arm, params, bc_state, args)
        train = buffers(seed=0)  # the same batches for every arm
        ema = make_ema(loss.actor, power=0.75) if arm.endswith("_ema") else None
        if arm == "fresh_adam_bc_ema":
            ema.n_averaged.copy_(bc_state["ema_n_averaged"])
        read = loss if ema is None else algorithm.build(ema.module, cfg.finetune)
        curve = [{"updates": 0, "held_loss": held_loss(read, held)}]
        t0 = time.perf_counter()
        for n in range(1, args.updates + 1):
            out = loss(train.sample_offline())
            opt.zero_grad(set_to_none=True)
            out["loss_bc"].backward()
            opt.step()
            if sched is not None:
                sched.step()
            if ema is not None:
                ema.update_parameters(loss.actor)
            if n in args.reads:
                curve.append({"updates": n, "held_loss": held_loss(read, held)})
                print(arm, curve[-1], flush=True)
        results[arm] = {"curve": curve, "seconds": time.perf_counter() - t0}
    save_results(
        args.out,
        {
            **settings,
            "demo_episodes": held_from.demo_episodes,
            "arms": results,
            "machine": machine_info(),
        },
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
