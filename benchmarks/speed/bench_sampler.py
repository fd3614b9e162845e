"""Chunk sampling speed against the training step it feeds, measured in the same run.

Samples windows (To=2, H=16, batch 256) from memory-mapped storage of state steps (D=35, A=4, as
ManiSkill PushCube) and of 128x128 RGB steps, and times one training step
of the default network (``L1FlowActor.for_state(..., down_dims=(64, 128, 256))`` + ``L1FlowLoss`` +
AdamW) at the same batch size, on a fixed batch and fed by the buffer with ``prefetch=2``. Ratios
above 1 mean the sampler stays ahead of the model. The RGB sampler is compared with the state
network's step, a lower bound on any image network's step.

    python -m benchmarks.speed.bench_sampler [--quick] [--out benchmarks/results/sampler.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch
from tensordict import TensorDict

from benchmarks.lib.common import machine_info, parse_args, save_results
from l1flow_rl import L1FlowActor, L1FlowLoss
from l1flow_rl.data import make_chunk_buffer

OBS_DIM, ACTION_DIM, TO, H, BATCH = 35, 4, 2, 16, 256


def synthetic_steps(episodes: int, length: int, rgb: bool) -> TensorDict:
    n = episodes * length
    obs = torch.randn(n, OBS_DIM)
    observation = obs
    if rgb:
        image = torch.randint(0, 256, (n, 3, 128, 128), dtype=torch.uint8)
        observation = TensorDict({"state": obs, "rgb": image}, batch_size=[n])
    return TensorDict(
        {
            "episode": torch.arange(episodes).repeat_interleave(length),
            "observation": observation,
            "action": torch.rand(n, ACTION_DIM) * 2 - 1,
            "next": {"reward": torch.zeros(n, 1), "done": torch.zeros(n, 1, dtype=torch.bool)},
        },
        batch_size=[n],
    )


def chunks_per_second(rb, batches: int) -> float:
    rb.sample()  # warm-up: page-in, episode table
    start = time.perf_counter()
    for _ in range(batches):
        rb.sample()
    return batches * BATCH / (time.perf_counter() - start)


def make_step(device: torch.device):
    actor = L1FlowActor.for_state(
        OBS_DIM, ACTION_DIM, obs_horizon=TO, pred_horizon=H, down_dims=(64, 128, 256)
    )
    loss_fn = L1FlowLoss(actor.to(device))
    optim = torch.optim.AdamW(loss_fn.parameters(), lr=1e-4, betas=(0.95, 0.999), weight_decay=1e-6)

    def step(batch: TensorDict) -> None:
        batch = batch.select("observation", "action_chunk", "action_is_pad").to(device, non_blocking=True)
        loss = loss_fn(batch)["loss_l1flow"]
        optim.zero_grad(set_to_none=True)
        loss.backward()
        optim.step()

    return step


def train_chunks_per_second(step, feeds: dict, steps: int, device: torch.device) -> dict[str, float]:
    """Training chunks per second for each batch source; the sources take turns step by step, so a
    busy machine slows them alike."""
    for feed in feeds.values():
        for _ in range(2):
            step(feed())
    seconds = dict.fromkeys(feeds, 0.0)
    for _ in range(steps):
        for name, feed in feeds.items():
            start = time.perf_counter()
            step(feed())
            if device.type == "cuda":
                torch.cuda.synchronize()
            seconds[name] += time.perf_counter() - start
    return {name: steps * BATCH / s for name, s in seconds.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None, help="default: benchmarks/results/sampler[_quick].json")
    parser.add_argument("--state-batches", type=int, default=200)
    parser.add_argument("--rgb-batches", type=int, default=30)
    parser.add_argument("--train-steps", type=int, default=20)
    parser.add_argument(
        "--device", default="cuda" if torch.cuda.is_available() else "cpu", help="for training"
    )
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not speed")
    args = parse_args(parser, argv)
    # quick: a few episodes and batches through the same code (storage, prefetch, training step)
    sizes = {"state": (10, 40), "rgb": (4, 40)} if args.quick else {"state": (100, 100), "rgb": (40, 80)}
    if args.quick:
        args.state_batches, args.rgb_batches, args.train_steps = 3, 2, 2
    device = torch.device(args.device)
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory(prefix="l1flow-bench-sampler-") as tmp:
        state = synthetic_steps(*sizes["state"], rgb=False)  # about 100 PushCube demonstrations
        state_rb = make_chunk_buffer(state, TO, H, BATCH, seed=0, storage_dir=Path(tmp) / "state")
        state_prefetch = make_chunk_buffer(
            state, TO, H, BATCH, seed=0, storage_dir=Path(tmp) / "state", prefetch=2
        )
        rgb = synthetic_steps(*sizes["rgb"], rgb=True)  # full: 3200 frames, 157 MB
        rgb_rb = make_chunk_buffer(rgb, TO, H, BATCH, seed=0, storage_dir=Path(tmp) / "rgb")
        del rgb
        results = {
            "state_chunks_per_s": chunks_per_second(state_rb, args.state_batches),
            "rgb128_chunks_per_s": chunks_per_second(rgb_rb, args.rgb_batches),
        }
        step = make_step(device)
        fixed = state_rb.sample()
        rates = train_chunks_per_second(
            step, {"fixed": lambda: fixed, "buffer": state_prefetch.sample}, args.train_steps, device
        )
        results["train_chunks_per_s"] = rates["fixed"]
        # the same loop fed by the buffer, two batches prefetched by background threads
        results["train_from_buffer_chunks_per_s"] = rates["buffer"]
    train = results["train_chunks_per_s"]
    figures = {
        "machine": machine_info(device),
        "quick": args.quick,
        "train_device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "batch_size": BATCH,
        "obs_horizon": TO,
        "pred_horizon": H,
        **{k: round(v, 1) for k, v in results.items()},
        "state_sampler_over_train": round(results["state_chunks_per_s"] / train, 2),
        "rgb128_sampler_over_train": round(results["rgb128_chunks_per_s"] / train, 2),
        "train_from_buffer_over_fixed_batch": round(results["train_from_buffer_chunks_per_s"] / train, 3),
    }
    out = save_results(args.out or f"benchmarks/results/sampler{'_quick' * args.quick}.json", figures)
    print(json.dumps(figures, indent=2))
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
