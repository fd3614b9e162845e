"""CUDA per-chunk latency at batch 1: L1 Flow 2-NFE eager and captured, against diffusers' DDPM-100 and
DDIM-16 eager loops around the same network, all in one run. Needs a CUDA GPU; refuses to run without.

Arms, for each network (``bench_latency``'s state network, and the PushT-size image network: 96x96
RGB cropped to 84 + agent position, ResNet-18 GroupNorm encoder, UNet 256/512/1024):

* ``l1flow_2nfe``: the actor called as the evaluator calls it (eager, with its input checks);
* ``l1flow_2nfe_cuda_graph``: the same call (observation in, executable chunk out, fresh noise on
  every replay) recorded once as a CUDA graph with ``torch.cuda.graph`` and replayed after copying
  the new observation into the graph's input tensors;
* ``l1flow_2nfe_cuda_graph_bf16``: the same graph recorded under bf16 autocast;
* ``l1flow_2nfe_reduce_overhead``: the policy's forward under ``torch.compile(mode="reduce-overhead")``
  (CUDA graphs through inductor); an error is recorded instead of a time if it fails to compile;
* ``floor_2_unet``, ``diffusers_ddpm100``, ``diffusers_ddim16``: ``bench_latency``'s floor and
  Diffusion Policy's scheduler loop, eager.

Goals (issue 13): >= 1000 chunks/s for the image network captured; >= 100x over diffusers DDPM-100.

    python -m benchmarks.speed.bench_latency_cuda [--quick] [--out PATH]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

if __package__ in (None, ""):  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.lib.common import format_table, interleaved, machine_info, parse_args, save_results
from benchmarks.speed.bench_latency import OBS_DIM, _floor_call, diffusers_calls
from benchmarks.speed.bench_latency import build_actor as build_state_actor
from l1flow_rl.config import NetworkConfig, PolicyConfig
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.utils.value_checks import skip_value_checks
from l1flow_rl.workspace.build import build_actor

NO_CUDA = (
    "bench_latency_cuda measures CUDA latency and needs a CUDA GPU, but torch sees none here "
    "(torch {version}); run benchmarks/speed/bench_latency.py for CPU latency"
)
IMAGE_SIDE, IMAGE_STATE_DIM, IMAGE_ACTION_DIM = 96, 2, 2


class CapturedActor:
    """An actor's whole call at one fixed batch, recorded once as a CUDA graph and replayed.

    The graph reads its observation from tensors it owns (``static_obs``); a call copies the new
    observation into them, replays, and returns the graph's output tensor (overwritten by the next
    call). The sampler's noise comes from the CUDA generator, which graphs advance per replay, so
    every replay draws fresh noise. Value checks read tensors on the host, which capture forbids;
    they are skipped inside the graph.
    """

    def __init__(
        self, actor: L1FlowActor, example: TensorDictBase, warmup: int = 3, bf16: bool = False
    ) -> None:
        self.actor = actor
        self.static_obs = example.clone()
        out_key = actor.out_keys[0]
        # bf16: the network's matrix work under autocast (cache off, as capture needs); the sampler's
        # arithmetic and the returned chunk stay float32.
        amp = torch.autocast("cuda", dtype=torch.bfloat16, enabled=bf16, cache_enabled=False)
        with torch.no_grad(), skip_value_checks(), amp:
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):  # warm-up off the capture stream, as torch's docs do
                for _ in range(warmup):
                    actor(self.static_obs.copy())
            torch.cuda.current_stream().wait_stream(side)
            self.graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self.graph):
                self.static_out = actor(self.static_obs.copy()).get(out_key)

    def __call__(self, observation: TensorDictBase) -> torch.Tensor:
        self.static_obs.update_(observation)
        self.graph.replay()
        return self.static_out


def image_actor(device: torch.device, quick: bool) -> L1FlowActor:
    network = {**_plain(NetworkConfig()), "down_dims": [32, 64, 128] if quick else [256, 512, 1024]}
    shapes = {"agent_pos": (IMAGE_STATE_DIM,), "img": (3, IMAGE_SIDE, IMAGE_SIDE)}
    encoder = {"name": "resnet18_gn", "crop_ratio": 0.875}
    return build_actor(_plain(PolicyConfig()), shapes, IMAGE_ACTION_DIM, encoder, network).to(device).eval()


def _plain(config: PolicyConfig | NetworkConfig) -> dict[str, Any]:
    import dataclasses

    return dataclasses.asdict(config)


def observation(name: str, device: torch.device) -> TensorDict:
    to = PolicyConfig().obs_horizon
    if name == "state":
        return TensorDict({"observation": torch.randn(1, to, OBS_DIM)}, [1], device=device)
    obs = TensorDict(
        {
            "agent_pos": torch.randn(1, to, IMAGE_STATE_DIM),
            "img": torch.randint(0, 256, (1, to, 3, IMAGE_SIDE, IMAGE_SIDE), dtype=torch.uint8),
        },
        [1, to],
    )
    return TensorDict({"observation": obs}, [1], device=device)


def latency_calls(
    actor: L1FlowActor, obs: TensorDict, peers: bool, errors: dict[str, str]
) -> dict[str, Callable[[], object]]:
    @torch.inference_mode()
    def eager() -> None:
        actor(obs.clone())

    captured = CapturedActor(actor, obs)
    captured_bf16 = CapturedActor(actor, obs, bf16=True)
    calls: dict[str, Callable[[], object]] = {
        "l1flow_2nfe": eager,
        "l1flow_2nfe_cuda_graph": lambda: captured(obs),
        "l1flow_2nfe_cuda_graph_bf16": lambda: captured_bf16(obs),
        "floor_2_unet": _floor_call(actor, obs),
    }
    try:
        compiled = torch.compile(actor.policy.forward, mode="reduce-overhead")

        def reduce_overhead() -> None:
            with torch.no_grad(), skip_value_checks():
                compiled(obs.get("observation"))

        for _ in range(3):  # compile and record outside the timed rounds
            reduce_overhead()
        calls["l1flow_2nfe_reduce_overhead"] = reduce_overhead
    except Exception as err:  # a compile failure is a figure of its own, not a crash
        errors["l1flow_2nfe_reduce_overhead"] = f"{type(err).__name__}: {err}"[:500]
    if peers:
        calls.update(diffusers_calls(actor, obs))
    return calls


def run(args: argparse.Namespace) -> dict[str, Any]:
    device = torch.device("cuda")
    torch.manual_seed(0)
    # cuDNN's autotuner picks each convolution's fastest algorithm for these exact shapes (the
    # default heuristics can pick slow ones for batch-1 1-D convolutions); it applies to every arm.
    torch.backends.cudnn.benchmark = args.cudnn_benchmark
    figures: dict[str, Any] = {
        "machine": machine_info(device),
        "quick": args.quick,
        "cudnn_benchmark": args.cudnn_benchmark,
        "batch": 1,
        "networks": {},
    }
    for name in args.networks:
        actor = (
            build_state_actor("l1flow_2nfe", device) if name == "state" else image_actor(device, args.quick)
        )
        obs = observation(name, device)
        errors: dict[str, str] = {}
        ms = interleaved(latency_calls(actor, obs, not args.no_peers, errors), args.rounds, device, warmup=3)
        ref, graph = ms["l1flow_2nfe"]["wall_ms"], ms["l1flow_2nfe_cuda_graph"]["wall_ms"]
        block: dict[str, Any] = {
            "parameters": sum(p.numel() for p in actor.parameters()),
            "ms": {k: {m: round(v, 4) for m, v in r.items()} for k, r in ms.items()},
            "chunks_per_s": {k: round(1e3 / r["wall_ms"], 1) for k, r in ms.items()},
            "cuda_graph_speedup_over_eager": round(ref / graph, 2),
            "errors": errors,
        }
        if "diffusers_ddpm100" in ms:
            for peer in ("diffusers_ddpm100", "diffusers_ddim16"):
                block[f"eager_speedup_over_{peer}"] = round(ms[peer]["wall_ms"] / ref, 1)
                block[f"cuda_graph_speedup_over_{peer}"] = round(ms[peer]["wall_ms"] / graph, 1)
        figures["networks"][name] = block
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results/latency_cuda.json")
    parser.add_argument("--networks", nargs="+", choices=["state", "image"], default=["state", "image"])
    parser.add_argument("--rounds", type=int, default=50)
    parser.add_argument("--no-peers", action="store_true", help="skip diffusers' schedulers")
    parser.add_argument("--quick", action="store_true", help="small image UNet, 3 rounds: checks the script")
    parser.add_argument(
        "--cudnn-benchmark", action="store_true", help="let cuDNN autotune each convolution (every arm)"
    )
    args = parse_args(parser, argv)
    if not torch.cuda.is_available():
        parser.exit(2, NO_CUDA.format(version=torch.__version__) + "\n")
    if args.quick:
        args.rounds = 3
    figures = run(args)
    save_results(args.out, figures)
    for name, block in figures["networks"].items():
        rows = [
            {
                "method": k,
                "wall ms": v["wall_ms"],
                "cpu ms": v["cpu_ms"],
                "chunks/s": block["chunks_per_s"][k],
            }
            for k, v in block["ms"].items()
        ]
        print(f"\n{name} network ({block['parameters']:,} parameters), batch 1, {figures['machine']['gpu']}:")
        print(format_table(rows, ["method", "wall ms", "cpu ms", "chunks/s"]))
        for key, err in block["errors"].items():
            print(f"{key}: not measured ({err})")
    print(f"\nsaved {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
