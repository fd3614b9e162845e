"""Image training throughput: the whole data path against the model alone, measured in the same run.

Both arms run the train job's step (``workspace.build_actor`` with the ``resnet18_gn`` encoder,
``build_loss``, ``Trainer``: AdamW, cosine LR, EMA) at the same batch:

* ``buffer``: ``rb.sample().to(device)`` from memory-mapped 128x128 uint8 RGB storage (the chunk
  buffer the train job uses), then the step;
* ``resident``: the step on one batch of random tensors of the same shapes and dtypes (uint8 images,
  float state and actions) already on the device.

The crop and the uint8 -> float conversion run inside the encoder on the device in both arms, so the
ratio ``buffer / resident`` (samples per second) is what the data path costs; the goal is >= 0.9.
The arms take turns each round, so that load drifting on a shared machine hits them alike.

    python -m benchmarks.speed.bench_image_train [--quick] [--device cuda] [--batch 64]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch
from tensordict import TensorDict

if __package__ in (None, ""):  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.lib.common import format_table, interleaved, machine_info, parse_args, save_results
from benchmarks.speed.bench_image_latency import rgb_setup
from l1flow_rl.data import make_chunk_buffer
from l1flow_rl.workspace.build import build_actor, build_loss
from l1flow_rl.workspace.trainer import Trainer

STATE_DIM, ACTION_DIM, SIDE = 25, 4, 128  # ManiSkill PushCube rgb: proprioception + TCP pose, 128x128


def synthetic_episodes(episodes: int, length: int) -> TensorDict:
    n = episodes * length
    g = torch.Generator().manual_seed(0)
    return TensorDict(
        {
            "episode": torch.arange(episodes).repeat_interleave(length),
            "observation": TensorDict(
                {
                    "state": torch.randn(n, STATE_DIM, generator=g),
                    "rgb": torch.randint(0, 256, (n, 3, SIDE, SIDE), dtype=torch.uint8, generator=g),
                },
                batch_size=[n],
            ),
            "action": torch.rand(n, ACTION_DIM, generator=g) * 2 - 1,
            "next": {"reward": torch.zeros(n, 1), "done": torch.zeros(n, 1, dtype=torch.bool)},
        },
        batch_size=[n],
    )


def resident_batch(sample: TensorDict, device: torch.device) -> TensorDict:
    """Random tensors with the sample's keys, shapes and dtypes, on the device."""

    def rand_like(x: torch.Tensor) -> torch.Tensor:
        if x.dtype == torch.uint8:
            return torch.randint(0, 256, x.shape, dtype=torch.uint8, device=device)
        if x.is_floating_point():
            return torch.rand(x.shape, device=device) * 2 - 1
        return x.to(device)

    return sample.apply(rand_like, device=device)


def run(args: argparse.Namespace) -> dict:
    device, cfg = rgb_setup(args)
    pcfg = cfg.policy
    shapes = {"state": (STATE_DIM,), "rgb": (3, SIDE, SIDE)}
    actor = build_actor(pcfg, shapes, ACTION_DIM, cfg.encoder, cfg.network).to(device)
    loss_fn = build_loss(actor, pcfg)
    trainer = Trainer(actor, loss_fn, total_steps=10**6, lr=1e-4, warmup_steps=0)
    with tempfile.TemporaryDirectory() as tmp:
        episodes = synthetic_episodes(args.episodes, args.length)
        rb = make_chunk_buffer(
            episodes,
            obs_horizon=pcfg.obs_horizon,
            pred_horizon=pcfg.pred_horizon,
            batch_size=args.batch,
            seed=0,
            storage_dir=Path(tmp) / "steps",
            prefetch=args.prefetch or None,
        )
        stored = rb.storage._storage.get(("observation", "rgb"))
        resident = resident_batch(rb.sample(), device)
        calls = {
            "buffer": lambda: trainer.train_step(rb.sample().to(device)),
            "resident": lambda: trainer.train_step(resident),
        }
        ms = interleaved(calls, rounds=args.rounds, device=device, warmup=1)
        storage = {"rgb_dtype": str(stored.dtype), "rgb_storage": type(stored).__name__}
    rate = {k: args.batch / (v["wall_ms"] / 1e3) for k, v in ms.items()}
    return {
        "machine": machine_info(device),
        "quick": args.quick,
        "setup": {
            "batch": args.batch,
            "obs_horizon": pcfg.obs_horizon,
            "pred_horizon": pcfg.pred_horizon,
            "image": [3, SIDE, SIDE],
            "crop_ratio": cfg.encoder.crop_ratio,
            "down_dims": list(cfg.network.down_dims),
            "steps_in_storage": args.episodes * args.length,
            "prefetch": args.prefetch,
            "rounds": args.rounds,
            "parameters": sum(p.numel() for p in actor.parameters()),
            **storage,
        },
        "step_ms": ms,
        "samples_per_s": rate,
        "buffer_over_resident": rate["buffer"] / rate["resident"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="batch 2, 2 rounds, small UNet (a smoke test)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--length", type=int, default=60)
    parser.add_argument("--prefetch", type=int, default=0, help="train.prefetch (the train job's default: 0)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--out", default="benchmarks/results/image_train.json")
    parser.add_argument("overrides", nargs="*", help="config overrides, e.g. network.down_dims=[32,64,128]")
    args = parse_args(parser, argv)
    if args.quick:
        args.batch, args.rounds, args.episodes, args.length = 2, 2, 2, 20
        args.overrides = ["network.down_dims=[16,32]", *args.overrides]
    figures = run(args)
    rows = [
        {"arm": k, "step_ms": v["wall_ms"], "cpu_ms": v["cpu_ms"], "samples/s": figures["samples_per_s"][k]}
        for k, v in figures["step_ms"].items()
    ]
    print(format_table(rows, ["arm", "step_ms", "cpu_ms", "samples/s"]))
    print(f"buffer / resident: {figures['buffer_over_resident']:.3f} (goal >= 0.9)")
    print(f"machine: {figures['machine']}")
    print(f"saved {save_results(args.out, figures)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
