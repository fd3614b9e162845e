"""Latency of the deployable policy (``l1flow_rl.export.program``) against the eager actor, per
chunk, on CPU at batch 1 and in the same run: what a robot gains or pays by running the exported
program instead of the library.

Networks: the state UNet ``l1flow-rl train`` builds by default (ConditionalUnet1D 64/128/256, D=35,
A=4, To=2, H=16, K=8) and, with ``--network image`` or ``both``, the image task's (ResNet-18 GroupNorm
encoder on 128x128 RGB plus a 25-D state), each with L1 Flow's 2-NFE sampler. Timed, taking turns
each round so that drifting load hits them alike:

* ``eager_actor``: ``L1FlowActor`` on a TensorDict (what a TorchRL loop calls), noise drawn inside;
* ``eager_policy``: ``actor.policy(obs, noise=noise)``, the same call on plain tensors;
* ``exported``: the ``torch.export`` program loaded back with ``torch.export.load`` (torch alone);
* ``onnxruntime``: the ONNX model in an onnxruntime session (one intra-op thread), when installed.

Reported: median wall and process-CPU milliseconds, each path's ratio to ``eager_actor``, and the
largest difference of the exported program's and ONNX's actions from eager for the same noise.
``--threads`` defaults to 1 (a busy 2-core machine).

    python -m benchmarks.speed.bench_export_latency [--quick] [--network state|image|both] [--out PATH]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import torch
from tensordict import TensorDict

from benchmarks.lib.common import (
    RESULTS_DIR,
    format_table,
    interleaved,
    machine_info,
    parse_args,
    save_results,
)
from benchmarks.speed.bench_latency import ACTION_DIM, OBS_DIM, _image_setup
from l1flow_rl.config import NetworkConfig, PolicyConfig
from l1flow_rl.export.program import export_onnx, export_program, load_program
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.workspace.build import build_actor

RESULTS = RESULTS_DIR / "export_latency.json"


def _actor(network: str, quick: bool) -> L1FlowActor:
    if network == "image":
        policy, encoder, net, shapes = _image_setup(quick)
        return build_actor(policy, shapes, ACTION_DIM, encoder, net).eval()
    net = NetworkConfig(down_dims=[16, 32]) if quick else NetworkConfig()
    policy, net = dataclasses.asdict(PolicyConfig()), dataclasses.asdict(net)
    return build_actor(policy, {"state": (OBS_DIM,)}, ACTION_DIM, None, net).eval()


def _inputs(actor: L1FlowActor, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Batch-1 observation entries (random images, states) and noise, in the program's input order."""
    g = torch.Generator().manual_seed(seed)
    p = actor.policy
    entries = [
        torch.randint(0, 256, (1, p.obs_horizon, *s), dtype=torch.uint8, generator=g)
        if len(s) == 3
        else torch.randn(1, p.obs_horizon, *s, generator=g)
        for s in p.encoder.obs_shapes.values()
    ]
    return (*entries, torch.randn(1, p.pred_horizon, p.action_dim, generator=g))


def measure(network: str, rounds: int, quick: bool, folder: Path) -> dict:
    actor = _actor(network, quick)
    inputs = _inputs(actor)
    *entries, noise = inputs
    names = list(actor.policy.encoder.obs_shapes)
    obs = entries[0] if names == ["state"] else TensorDict(dict(zip(names, entries)), batch_size=[1])
    td = TensorDict({"observation": obs}, batch_size=[1])
    export_program(actor, folder / f"{network}.pt2")
    program = load_program(folder / f"{network}.pt2")
    with torch.inference_mode():
        eager = actor.policy(obs, noise=noise)
        diffs = {"exported": float((program(*inputs) - eager).abs().max())}
    calls: dict[str, Callable[[], object]] = {
        "eager_actor": lambda: actor(td.clone()),
        "eager_policy": lambda: actor.policy(obs, noise=noise),
        "exported": lambda: program(*inputs),
    }
    try:
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = torch.get_num_threads()
        session = ort.InferenceSession(str(export_onnx(actor, folder / f"{network}.onnx")), options)
        feed = {n: t.numpy() for n, t in zip([*names, "noise"], inputs)}
        diffs["onnxruntime"] = float((torch.from_numpy(session.run(None, feed)[0]) - eager).abs().max())
        calls["onnxruntime"] = lambda: session.run(None, feed)
    except ImportError:
        pass
    with torch.inference_mode():
        timing = interleaved(calls, rounds, torch.device("cpu"), warmup=2)
    base = timing["eager_actor"]["wall_ms"]
    for name, row in timing.items():
        row["ratio_to_eager_actor"] = row["wall_ms"] / base
        if name in diffs:
            row["max_abs_diff_from_eager"] = diffs[name]
    return {"obs_shapes": {k: list(v) for k, v in actor.policy.encoder.obs_shapes.items()}, "paths": timing}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--network", choices=("state", "image", "both"), default="both")
    parser.add_argument("--rounds", type=int, default=50)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--quick", action="store_true", help="tiny networks, 3 rounds: checks the script")
    parser.add_argument("--out", type=Path, default=None)
    args = parse_args(parser, argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    rounds = 3 if args.quick else args.rounds
    networks = ["state", "image"] if args.network == "both" else [args.network]
    figures: dict = {"quick": args.quick, "batch": 1, "device": "cpu", "rounds": rounds, "networks": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for network in networks:
            figures["networks"][network] = measure(network, rounds, args.quick, Path(tmp))
            rows = [{"path": k, **v} for k, v in figures["networks"][network]["paths"].items()]
            print(f"{network} network, batch 1, cpu, {args.threads} thread(s), median of {rounds} rounds")
            columns = ["path", "wall_ms", "cpu_ms", "ratio_to_eager_actor", "max_abs_diff_from_eager"]
            print(format_table(rows, columns))
    figures["machine"] = machine_info("cpu")
    out = args.out or (RESULTS.with_name("export_latency_quick.json") if args.quick else RESULTS)
    print(f"wrote {save_results(out, figures)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
