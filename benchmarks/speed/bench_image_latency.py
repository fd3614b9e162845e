"""Per-chunk inference latency with the image encoder, against its floor, measured in the same run.

``actor``: the L1 Flow actor as the evaluator calls it (``workspace.build_actor`` with the
``resnet18_gn`` encoder, eval mode): observation checks, normalisation, uint8 -> float and centre
crop, the encoder once, the two-step sampler's 2 UNet passes, unnormalisation.
``floor``: the encoder once (including its crop and conversion) plus 2 UNet forwards, timed alone.
The goal is ``actor / floor <= 1.05``: everything around the networks costs little. Batch 1 (one
robot) and a batch of parallel envs; the calls take turns each round.

    python -m benchmarks.speed.bench_image_latency [--quick] [--device cuda]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

if __package__ in (None, ""):  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.lib.common import format_table, interleaved, machine_info, parse_args, save_results
from benchmarks.speed.bench_latency import _floor_call
from l1flow_rl.commands.cli import compose_config
from l1flow_rl.workspace.build import build_actor

STATE_DIM, ACTION_DIM, SIDE = 25, 4, 128  # ManiSkill PushCube rgb


def observation(batch: int, obs_horizon: int, device: torch.device) -> TensorDict:
    obs = TensorDict(
        {
            "state": torch.randn(batch, obs_horizon, STATE_DIM),
            "rgb": torch.randint(0, 256, (batch, obs_horizon, 3, SIDE, SIDE), dtype=torch.uint8),
        },
        batch_size=[batch, obs_horizon],
    )
    return TensorDict({"observation": obs}, batch_size=[batch]).to(device)


def calls_for(actor, td: TensorDict) -> dict:
    @torch.inference_mode()
    def full() -> None:
        actor(td.clone())

    return {"actor": full, "floor": _floor_call(actor, td)}


def rgb_setup(args: argparse.Namespace) -> tuple[torch.device, Any]:
    """The device and the RGB PushCube config both image benchmarks build their policy from (torch's
    threads and seed set first)."""
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cfg = compose_config(["task=maniskill_pushcube_rgb", "encoder=resnet18_gn", *args.overrides])
    return torch.device(args.device), cfg


def run(args: argparse.Namespace) -> dict:
    device, cfg = rgb_setup(args)
    shapes = {"state": (STATE_DIM,), "rgb": (3, SIDE, SIDE)}
    actor = build_actor(cfg.policy, shapes, ACTION_DIM, cfg.encoder, cfg.network).to(device).eval()
    assert actor.sampler.nfe == 2, f"policy {cfg.policy.name!r} is not the 2-NFE L1 Flow policy"
    figures: dict = {
        "machine": machine_info(device),
        "quick": args.quick,
        "setup": {
            "image": [3, SIDE, SIDE],
            "crop_ratio": cfg.encoder.crop_ratio,
            "obs_horizon": cfg.policy.obs_horizon,
            "down_dims": list(cfg.network.down_dims),
            "rounds": args.rounds,
            "parameters": sum(p.numel() for p in actor.parameters()),
        },
        "inference": {},
    }
    for batch in args.batches:
        ms = interleaved(
            calls_for(actor, observation(batch, cfg.policy.obs_horizon, device)), args.rounds, device
        )
        figures["inference"][f"batch{batch}"] = {
            "ms": ms,
            "actor_over_floor": ms["actor"]["wall_ms"] / ms["floor"]["wall_ms"],
        }
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="2 rounds, batch 1, small UNet (a smoke test)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument("--out", default="benchmarks/results/image_latency.json")
    parser.add_argument("overrides", nargs="*", help="config overrides, e.g. network.down_dims=[32,64,128]")
    args = parse_args(parser, argv)
    if args.quick:
        args.rounds, args.batches = 2, [1]
        args.overrides = ["network.down_dims=[16,32]", *args.overrides]
    figures = run(args)
    rows = []
    for name, block in figures["inference"].items():
        for call, v in block["ms"].items():
            rows.append({"batch": name, "call": call, "wall_ms": v["wall_ms"], "cpu_ms": v["cpu_ms"]})
        print(f"{name}: actor / floor = {block['actor_over_floor']:.3f} (goal <= 1.05)")
    print(format_table(rows, ["batch", "call", "wall_ms", "cpu_ms"]))
    print(f"machine: {figures['machine']}")
    print(f"saved {save_results(args.out, figures)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
