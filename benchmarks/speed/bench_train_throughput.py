"""Training throughput: the Trainer's whole step against the bare model update, measured in the same run.

For each network and each setting of bf16 autocast and ``torch.compile`` (the Trainer's ``amp`` and
``compile`` options), three arms take turns each round, all on one actor and one AdamW:

* ``trainer``: what ``l1flow-rl train`` runs per step: ``buffer.sample().to(device)`` from the chunk
  replay buffer, then ``Trainer.train_step`` (loss module, backward, gradient norm, AdamW, cosine
  LR, EMA; value checks off, as the train job runs it);
* ``trainer_resident``: ``Trainer.train_step`` on a batch already on the device (the buffer's cost
  is the gap to ``trainer``);
* ``model``: the floor: encoder and UNet forward on resident tensors of the same shapes, an L1 loss,
  backward and ``AdamW.step()``, nothing else;
* ``trainer_pinned`` (CUDA only): as ``trainer``, the sample copied through pinned memory with
  ``non_blocking=True`` (a copy from pageable memory can make the host wait for the device).

Each timed call runs ``--steps-per-call`` consecutive steps and waits for the device only at its end,
so a step that never waits for the device (no host synchronisation) can overlap the next step's
host work with this one's GPU work, as in the train loop. Reported: milliseconds and samples per
second per arm, and ``trainer_over_model`` (samples/s of ``trainer`` over ``model``; goal >= 0.9).

Networks: ``state``, the default ``PolicyConfig`` and ``NetworkConfig`` (UNet 64/128/256) on a
35-dim state; ``image``, the paper-size image network: Diffusion Policy's PushT image setting (96x96
RGB cropped to 84, 2-dim agent position, 2-dim actions), the ResNet-18 GroupNorm encoder and a UNet
256/512/1024.

    python -m benchmarks.speed.bench_train_throughput [--quick] [--device cuda]
        [--networks state image] [--amp off on] [--compile off on]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

if __package__ in (None, ""):  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.lib.common import format_table, interleaved, machine_info, parse_args, save_results
from benchmarks.speed.bench_image_train import resident_batch
from l1flow_rl.config import NetworkConfig, PolicyConfig
from l1flow_rl.data import make_chunk_buffer
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.workspace.build import build_actor, build_loss
from l1flow_rl.workspace.trainer import Trainer

STATE_DIM, STATE_ACTION_DIM = 35, 4  # the state network's sizes, as in bench_latency
IMAGE_SIDE, IMAGE_STATE_DIM, IMAGE_ACTION_DIM = 96, 2, 2  # PushT image: pixels + agent position
IMAGE_CROP_RATIO, IMAGE_DOWN_DIMS = 0.875, [256, 512, 1024]  # 84 of 96; Diffusion Policy's UNet


@dataclasses.dataclass
class Network:
    """How to build one network and the episodes it trains on."""

    name: str
    obs_shapes: dict[str, tuple[int, ...]]
    action_dim: int
    policy: dict[str, Any]
    encoder: dict[str, Any] | None
    network: dict[str, Any]


def networks(quick: bool) -> dict[str, Network]:
    policy = dataclasses.asdict(PolicyConfig())
    network = dataclasses.asdict(NetworkConfig())
    image_network = {**network, "down_dims": [32, 64, 128] if quick else IMAGE_DOWN_DIMS}
    return {
        "state": Network("state", {"state": (STATE_DIM,)}, STATE_ACTION_DIM, policy, None, network),
        "image": Network(
            "image",
            {"agent_pos": (IMAGE_STATE_DIM,), "img": (3, IMAGE_SIDE, IMAGE_SIDE)},
            IMAGE_ACTION_DIM,
            policy,
            {"name": "resnet18_gn", "crop_ratio": IMAGE_CROP_RATIO},
            image_network,
        ),
    }


def synthetic_episodes(net: Network, episodes: int, length: int) -> TensorDict:
    """Random episodes with the network's observation entries (images as uint8, as stored)."""
    n = episodes * length
    g = torch.Generator().manual_seed(0)
    obs = {
        k: torch.randint(0, 256, (n, *s), dtype=torch.uint8, generator=g)
        if len(s) == 3
        else torch.randn(n, *s, generator=g)
        for k, s in net.obs_shapes.items()
    }
    observation: torch.Tensor | TensorDict = (
        obs["state"] if list(obs) == ["state"] else TensorDict(obs, batch_size=[n])
    )
    return TensorDict(
        {
            "episode": torch.arange(episodes).repeat_interleave(length),
            "observation": observation,
            "action": torch.rand(n, net.action_dim, generator=g) * 2 - 1,
            "next": {"reward": torch.zeros(n, 1), "done": torch.zeros(n, 1, dtype=torch.bool)},
        },
        batch_size=[n],
    )


def model_step(
    actor: L1FlowActor, optimizer: torch.optim.Optimizer, batch: TensorDict, amp: bool
) -> Callable[[], None]:
    """The bare update on resident tensors: encoder + UNet forward, L1 loss, backward, AdamW."""
    policy = actor.policy
    obs = policy.as_obs_dict(batch["observation"])  # reshaping only, done once
    x1 = batch["action_chunk"].reshape(-1, policy.pred_horizon, policy.action_dim)
    n = x1.shape[0]
    t = torch.rand(n, device=x1.device)
    x_t = torch.randn_like(x1)
    device_type = x1.device.type

    def step() -> None:
        autocast = torch.autocast(device_type, dtype=torch.bfloat16) if amp else contextlib.nullcontext()
        with autocast:
            cond = policy.encoder(obs).reshape(n, -1)
            loss = (policy.net(x_t, t, cond).float() - x1).abs().mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    return step


def repeat(fn: Callable[[], object], times: int) -> Callable[[], None]:
    def call() -> None:
        for _ in range(times):
            fn()

    return call


def measure(net: Network, amp: bool, compile: bool, args: argparse.Namespace) -> dict[str, Any]:
    device = torch.device(args.device)
    torch.manual_seed(0)
    actor = build_actor(net.policy, net.obs_shapes, net.action_dim, net.encoder, net.network).to(device)
    trainer = Trainer(
        actor,
        build_loss(actor, net.policy),
        total_steps=10**6,
        warmup_steps=0,
        amp=amp,
        compile=compile,
        check_values=False,  # as the train job runs it: the loader checked the values
    )
    buffer = make_chunk_buffer(
        synthetic_episodes(net, args.episodes, args.length),
        obs_horizon=net.policy["obs_horizon"],
        pred_horizon=net.policy["pred_horizon"],
        batch_size=args.batch[net.name],
        seed=0,
        prefetch=args.prefetch or None,
    )
    resident = resident_batch(buffer.sample(), device)
    k = args.steps_per_call
    arms = {
        "trainer": repeat(lambda: trainer.train_step(buffer.sample().to(device)), k),
        "trainer_resident": repeat(lambda: trainer.train_step(resident), k),
        "model": repeat(model_step(actor, trainer.optimizer, resident, amp), k),
    }
    if device.type == "cuda":  # the sample copied from pinned memory, without waiting for the copy
        arms["trainer_pinned"] = repeat(
            lambda: trainer.train_step(buffer.sample().pin_memory().to(device, non_blocking=True)), k
        )
    ms = interleaved(arms, rounds=args.rounds, device=device, warmup=args.warmup)
    batch = args.batch[net.name]
    per_step = {arm: {key: v / k for key, v in r.items()} for arm, r in ms.items()}
    rate = {arm: batch / (r["wall_ms"] / 1e3) for arm, r in per_step.items()}
    result = {
        "amp_bf16": amp,
        "compile": compile,
        "step_ms": {arm: {key: round(v, 3) for key, v in r.items()} for arm, r in per_step.items()},
        "samples_per_s": {arm: round(v, 2) for arm, v in rate.items()},
        # samples/s of each arm over the bare update's; trainer_over_model is the goal's figure (>= 0.9)
        **{f"{arm}_over_model": round(rate[arm] / rate["model"], 3) for arm in rate if arm != "model"},
    }
    return result


def run(args: argparse.Namespace, out: str | None = None) -> dict[str, Any]:
    """Every network x setting; with ``out``, the figures so far are saved after each setting, so a
    run stopped part-way (a machine taken back, compilation taking longer than planned) keeps
    what it measured (``"complete": false`` until the last setting)."""
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    figures: dict[str, Any] = {"machine": machine_info(device), "quick": args.quick, "complete": False}
    figures["setup"] = {
        "batch": args.batch,
        "rounds": args.rounds,
        "warmup_calls": args.warmup,
        "steps_per_call": args.steps_per_call,
        "episodes_x_length": [args.episodes, args.length],
        "prefetch": args.prefetch,
    }
    figures["networks"] = {}
    for name in args.networks:
        net = networks(args.quick)[name]
        probe = build_actor(net.policy, net.obs_shapes, net.action_dim, net.encoder, net.network)
        block: dict[str, Any] = {
            "obs_shapes": {k: list(v) for k, v in net.obs_shapes.items()},
            "action_dim": net.action_dim,
            "down_dims": list(net.network["down_dims"]),
            "encoder": (net.encoder or {"name": "state"})["name"],
            "parameters": sum(p.numel() for p in probe.parameters()),
            "settings": {},
        }
        del probe
        for amp in args.amp:
            for comp in args.compile:
                key = f"{'bf16' if amp == 'on' else 'fp32'}_{'compiled' if comp == 'on' else 'eager'}"
                block["settings"][key] = measure(net, amp == "on", comp == "on", args)
                if device.type == "cuda":
                    torch.cuda.empty_cache()  # the next setting builds its own model
                print(f"{name} {key}: {block['settings'][key]['trainer_over_model']}x", flush=True)
                figures["networks"][name] = block
                if out is not None:
                    save_results(out, figures)
    figures["machine"]["load_average_1min_end"] = machine_info(device)["load_average_1min"]
    figures["complete"] = True
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny batch, 1 round, small image UNet")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--networks", nargs="+", choices=["state", "image"], default=["state", "image"])
    parser.add_argument("--amp", nargs="+", choices=["off", "on"], default=["off", "on"])
    parser.add_argument("--compile", nargs="+", choices=["off", "on"], default=["off", "on"])
    parser.add_argument("--state-batch", type=int, default=256, help="the train job's default batch")
    parser.add_argument("--image-batch", type=int, default=64, help="Diffusion Policy's image batch")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2, help="untimed calls per arm (compilation)")
    parser.add_argument("--steps-per-call", type=int, default=10)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--length", type=int, default=100)
    parser.add_argument("--prefetch", type=int, default=0, help="train.prefetch (the train job's default: 0)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    parser.add_argument(
        "--out", default=None, help="default: benchmarks/results/train_throughput_<device>.json"
    )
    args = parse_args(parser, argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error("--device cuda: torch sees no CUDA device here")
    if args.quick:
        args.state_batch, args.image_batch, args.rounds, args.warmup = 4, 2, 1, 1
        args.steps_per_call, args.episodes, args.length = 1, 2, 20
    args.batch = {"state": args.state_batch, "image": args.image_batch}
    out = args.out or f"benchmarks/results/train_throughput_{torch.device(args.device).type}.json"
    figures = run(args, out)
    save_results(out, figures)
    for name, block in figures["networks"].items():
        rows = [
            {
                "setting": key,
                **{f"{arm} ms": r["step_ms"][arm]["wall_ms"] for arm in r["step_ms"]},
                "trainer/model": r["trainer_over_model"],
            }
            for key, r in block["settings"].items()
        ]
        print(f"\n{name} network ({block['parameters']:,} parameters), batch {args.batch[name]}:")
        columns = ["setting", "trainer ms", "trainer_pinned ms", "trainer_resident ms", "model ms"]
        print(format_table(rows, [*columns, "trainer/model"]))
    print(f"\nsaved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
