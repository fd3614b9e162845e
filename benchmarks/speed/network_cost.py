"""What each chunk denoiser costs on the CPU: ``network=unet`` against ``network=mlp``, same data.

Both networks are built from the config as ``l1flow-rl train network=<name>`` builds them (the
network group's defaults, L1 Flow's loss and 2-NFE sampler) on PushCube state's shapes, and measured
in the same process, so the ratios MLP / UNet compare like with like on this machine:

- ``train_step_ms``: one optimisation step of the train job's :class:`~l1flow_rl.workspace.trainer.Trainer`
  (loss, backward, AdamW, EMA update) on a batch of 256, with 1 and with 2 torch threads;
- ``chunk_ms``: one 2-NFE chunk of the actor's call (encode once, two network calls, un-normalise) at
  batch 1 and 64, with 1 and with 2 threads; ``chunk_rate_hz`` at batch 1 is 1000 / its median.

Each figure is the median over ``--reps`` timed calls after ``--warmup`` untimed ones. The goals it
is read against (issue 69): the MLP's training step >= 10x faster than the UNet's, and >= 1 kHz chunk
rate at batch 1 on the CPU.

    python -m benchmarks.speed.network_cost              # writes benchmarks/results/network_cost.json
    python -m benchmarks.speed.network_cost --quick      # a smoke run (a few calls, another file)
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from benchmarks.lib.common import RESULTS_DIR, machine_info, parse_args, save_results
from l1flow_rl.commands.cli import compose_config
from l1flow_rl.workspace.build import build_actor, build_loss
from l1flow_rl.workspace.trainer import Trainer

OUT = RESULTS_DIR / "network_cost.json"
# ManiSkill PushCube-v1, obs_mode=state, pd_ee_delta_pos: 35 state entries, 4 action dims (as the
# train job's demonstrations give them; benchmarks/bench_latency.py uses the same)
OBS_DIM, ACTION_DIM = 35, 4
TRAIN_BATCH = 256
CHUNK_BATCHES = (1, 64)
THREADS = (1, 2)
NETWORKS = ("unet", "mlp")


def _median_ms(fn: Callable[[], Any], warmup: int, reps: int) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1000 * statistics.median(times)


def _setup(network: str):
    cfg = compose_config([f"network={network}", "task=maniskill_pushcube", "policy=l1flow"])
    torch.manual_seed(0)
    actor = build_actor(cfg.policy, {"state": (OBS_DIM,)}, ACTION_DIM, None, cfg.network)
    p = actor.policy
    obs = torch.randn(TRAIN_BATCH, p.obs_horizon, OBS_DIM)
    chunk = torch.rand(TRAIN_BATCH, p.pred_horizon, ACTION_DIM) * 2 - 1
    p.fit_normalizers(observation=obs.reshape(-1, OBS_DIM), action=chunk.reshape(-1, ACTION_DIM))
    t = cfg.train
    trainer = Trainer(
        actor,
        build_loss(actor, cfg.policy),
        total_steps=10**6,
        lr=t.lr,
        betas=tuple(t.betas),
        weight_decay=t.weight_decay,
        warmup_steps=t.warmup_steps,
        ema_power=t.ema_power,
        check_values=False,  # as l1flow-rl train runs it (the loader has checked the episodes)
    )
    batch = TensorDict({"observation": obs, "action_chunk": chunk}, [TRAIN_BATCH])
    params = sum(q.numel() for q in p.net.parameters())
    return cfg, trainer, batch, params


def measure(network: str, warmup: int, reps: int) -> dict[str, Any]:
    cfg, trainer, batch, params = _setup(network)
    actor = trainer.actor
    out: dict[str, Any] = {
        "network": {k: v for k, v in OmegaConf.to_container(cfg.network).items() if v is not None},
        "parameters": params,
        "train_step_ms": {},
        "chunk_ms": {},
    }
    for threads in THREADS:
        torch.set_num_threads(threads)
        out["train_step_ms"][f"{threads}_threads"] = _median_ms(
            lambda: trainer.train_step(batch), warmup, reps
        )
    actor.eval()
    for threads in THREADS:
        torch.set_num_threads(threads)
        for b in CHUNK_BATCHES:
            td = TensorDict({"observation": batch["observation"][:b]}, [b])
            with torch.no_grad():
                ms = _median_ms(lambda td=td: actor(td), warmup, reps * 4)
            out["chunk_ms"][f"batch{b}_{threads}_threads"] = ms
    out["chunk_rate_hz_batch1_1_thread"] = 1000 / out["chunk_ms"]["batch1_1_threads"]
    return out


def run(warmup: int, reps: int) -> dict[str, Any]:
    threads_before = torch.get_num_threads()
    try:
        figures = {name: measure(name, warmup, reps) for name in NETWORKS}
    finally:
        torch.set_num_threads(threads_before)
    unet, mlp = figures["unet"], figures["mlp"]
    ratios = {
        "train_step_mlp_over_unet": {
            k: mlp["train_step_ms"][k] / unet["train_step_ms"][k] for k in unet["train_step_ms"]
        },
        "chunk_mlp_over_unet": {k: mlp["chunk_ms"][k] / unet["chunk_ms"][k] for k in unet["chunk_ms"]},
    }
    speedup_1t = 1 / ratios["train_step_mlp_over_unet"]["1_threads"]
    rate = mlp["chunk_rate_hz_batch1_1_thread"]
    return {
        "data": {"obs_dim": OBS_DIM, "action_dim": ACTION_DIM, "train_batch": TRAIN_BATCH},
        "repetitions": {"warmup": warmup, "train_step": reps, "chunk": reps * 4, "statistic": "median"},
        "figures": figures,
        "ratios": ratios,
        "goals": {
            "train_step_speedup_1_thread": speedup_1t,
            "train_step_speedup_at_least_10x": speedup_1t >= 10,
            "mlp_chunk_rate_hz_batch1_1_thread": rate,
            "mlp_chunk_rate_at_least_1khz": rate >= 1000,
        },
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=10, help="timed training steps per figure (chunks: 4x)")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="2 timed calls, 1 warm-up: a smoke run")
    parser.add_argument("--out", type=Path, default=None)
    args = parse_args(parser, argv)  # the command, arguments and commit go into the saved file
    warmup, reps = (1, 2) if args.quick else (args.warmup, args.reps)
    out = args.out or (OUT.with_name("network_cost_quick.json") if args.quick else OUT)
    record = {"machine": machine_info(torch.device("cpu")), "quick": args.quick, **run(warmup, reps)}
    save_results(out, record)
    g, r = record["goals"], record["ratios"]
    print(
        f"train step (batch {TRAIN_BATCH}) MLP/UNet: {r['train_step_mlp_over_unet']}; "
        f"speed-up at 1 thread {g['train_step_speedup_1_thread']:.1f}x\n"
        f"chunk MLP/UNet: {r['chunk_mlp_over_unet']}\n"
        f"MLP chunk rate at batch 1, 1 thread: {g['mlp_chunk_rate_hz_batch1_1_thread']:.0f} Hz\nwrote {out}"
    )
    return record


if __name__ == "__main__":
    main()
