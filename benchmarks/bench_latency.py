"""Training-step time and per-chunk inference latency of the default state network, in one run.

The network is the one ``l1flow-rl train`` builds by default (``PolicyConfig``: ConditionalUnet1D
with down_dims 64/128/256, To=2, H=16, K=8) for a ManiSkill-PushCube-sized state (D=35, A=4).

* Training: one AdamW step of each loss at batch 256 (L1 Flow, v-flow, DDPM, regression).
* Inference: one action chunk at batch 1 through ``L1FlowActor`` (observation in, executable window
  out) for L1 Flow's 2-NFE two-step sampler against a v-flow Euler-10, DDIM-16 and DDPM-100 on the
  same network, and regression's single pass. Speed-ups are ratios to L1 Flow measured in this run.

Every figure is a median over repetitions, and the methods take turns within each round so that
load drifting on a shared machine hits them alike. Both wall-clock and this process's CPU time are
reported. ``--threads`` defaults to 1: on a busy 2-core machine torch's intra-op threads spin-wait
and made small kernels several times slower (measured), and a policy in a control loop usually
runs single-threaded anyway.

    .venv/bin/python benchmarks/bench_latency.py [--threads 1] [--out benchmarks/results/latency.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from tensordict import TensorDict

from l1flow_rl import DiffusionLoss, FlowMatchingLoss, L1FlowActor, L1FlowLoss, RegressionLoss
from l1flow_rl.config import PolicyConfig
from l1flow_rl.workspace.build import build_actor as build_policy_actor

OBS_DIM, ACTION_DIM, BATCH = 35, 4, 256

#: name -> (sampler, loss that trains a network for it)
# method -> (sampler name and options in the policy config, loss)
METHODS = {
    "l1flow_2nfe": (("two_step", {"t_first": 0.5}), L1FlowLoss),
    "flow_euler10": (("velocity_euler", {"steps": 10}), FlowMatchingLoss),
    "ddim16": (("ddim", {"steps": 16}), DiffusionLoss),
    "ddpm100": (("ddpm", {}), DiffusionLoss),
    "regression": (("direct", {}), RegressionLoss),
}
TRAINED = ("l1flow_2nfe", "flow_euler10", "ddpm100", "regression")  # DDIM trains like DDPM


def build_actor(name: str, device: torch.device) -> L1FlowActor:
    """The default policy config's network, built as the train job builds it, with ``name``'s sampler."""
    sampler, options = METHODS[name][0]
    cfg = dataclasses.replace(PolicyConfig(), sampler=sampler, sampler_kwargs=options)
    return build_policy_actor(dataclasses.asdict(cfg), {"state": (OBS_DIM,)}, ACTION_DIM).to(device)


def timed(fn: Callable[[], None], device: torch.device) -> tuple[float, float]:
    """(wall seconds, process CPU seconds) of one call."""
    wall, cpu = time.perf_counter(), time.process_time()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - wall, time.process_time() - cpu


def interleaved(fns: dict[str, Callable[[], None]], rounds: int, device: torch.device) -> dict[str, dict]:
    """Median wall and CPU milliseconds per call; the functions take turns each round."""
    for fn in fns.values():  # warm-up
        timed(fn, device)
    walls: dict[str, list[float]] = {k: [] for k in fns}
    cpus: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            w, c = timed(fn, device)
            walls[name].append(w)
            cpus[name].append(c)
    return {
        k: {"wall_ms": 1e3 * statistics.median(walls[k]), "cpu_ms": 1e3 * statistics.median(cpus[k])}
        for k in fns
    }


def training_steps(device: torch.device) -> dict[str, Callable[[], None]]:
    p = PolicyConfig()
    batch = TensorDict(
        {
            "observation": torch.randn(BATCH, p.obs_horizon, OBS_DIM),
            "action_chunk": torch.rand(BATCH, p.pred_horizon, ACTION_DIM) * 2 - 1,
        },
        [BATCH],
        device=device,
    )
    steps = {}
    for name in TRAINED:
        loss_fn = METHODS[name][1](build_actor(name, device))
        optim = torch.optim.AdamW(loss_fn.parameters(), lr=1e-4, betas=(0.95, 0.999), weight_decay=1e-6)

        def step(loss_fn=loss_fn, optim=optim) -> None:
            loss = loss_fn(batch)[loss_fn.loss_name]
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()

        steps[name] = step
    return steps


def inference_calls(device: torch.device) -> dict[str, Callable[[], None]]:
    obs = TensorDict({"observation": torch.randn(1, PolicyConfig().obs_horizon, OBS_DIM)}, [1], device=device)
    calls = {}
    for name in METHODS:
        actor = build_actor(name, device).eval()

        @torch.inference_mode()
        def call(actor=actor) -> None:
            actor(obs.clone())

        calls[name] = call
    return calls


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results/latency.json")
    parser.add_argument(
        "--threads", type=int, default=1, help="torch intra-op threads (0: leave torch's default)"
    )
    parser.add_argument("--train-rounds", type=int, default=10)
    parser.add_argument("--infer-rounds", type=int, default=15)
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    args = parser.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    torch.manual_seed(0)

    load_before = os.getloadavg()[0]
    train = interleaved(training_steps(device), args.train_rounds, device)
    infer = interleaved(inference_calls(device), args.infer_rounds, device)
    ref = infer["l1flow_2nfe"]
    n_params = sum(p.numel() for p in build_actor("l1flow_2nfe", device).parameters())
    figures = {
        "machine": f"{platform.machine()} {os.cpu_count()} cores, torch threads {torch.get_num_threads()}",
        # other processes' load: with load above the core count, wall time exceeds CPU time
        "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "network": {
            "obs_dim": OBS_DIM,
            "action_dim": ACTION_DIM,
            "down_dims": PolicyConfig().down_dims,
            "timestep_embed_dim": PolicyConfig().timestep_embed_dim,
            "parameters": n_params,
        },
        "train_step_batch256_ms": {k: {m: round(v, 1) for m, v in r.items()} for k, r in train.items()},
        "chunk_latency_batch1_ms": {k: {m: round(v, 2) for m, v in r.items()} for k, r in infer.items()},
        "nfe": {k: METHODS[k][0]().nfe for k in METHODS},
        "speedup_of_l1flow_wall": {k: round(r["wall_ms"] / ref["wall_ms"], 2) for k, r in infer.items()},
        "speedup_of_l1flow_cpu": {k: round(r["cpu_ms"] / ref["cpu_ms"], 2) for k, r in infer.items()},
        "l1flow_chunks_per_s_wall": round(1e3 / ref["wall_ms"], 1),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(figures, indent=2) + "\n")
    print(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
