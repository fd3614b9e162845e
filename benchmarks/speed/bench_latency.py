"""Per-chunk inference latency of one network under every sampler, beside the peers' own path and the
floor, plus the training-step time of each loss, all in one run (the paper's speed claim).

``--network state`` (default): the network ``l1flow-rl train`` builds by default (``PolicyConfig``
and ``NetworkConfig``, configs/network/unet.yaml: ConditionalUnet1D, down_dims 64/128/256, To=2,
H=16, K=8) for a ManiSkill-PushCube-sized state (D=35, A=4). ``--network mlp``: the same state policy
on ``network=mlp`` (configs/network/mlp.yaml, 4 x 512), saved as ``latency_mlp.json``. ``--network
image``: the one ``l1flow-rl train task=maniskill_pushcube_rgb`` builds (the same UNet behind the
ResNet-18 GroupNorm encoder, 128x128 RGB cropped to 0.9, plus a 25-D state), saved as
``latency_image.json``. Weights do not change the time, so one network serves every sampler.

Inference, one action chunk through ``L1FlowActor`` (observation in, executable window out), at
batch 1 and 64:

* L1 Flow 2-NFE; sample-prediction Euler with 1/2/5/10 steps; v-prediction Euler 10;
  DDIM-16 and DDPM-100 (this project's samplers); plain regression (its UNet drops the timestep
  input, so it is the one network of its own);
* the distillation comparison's samplers: EDM Heun over 18 and 10 levels (35 and 19 NFE),
  Consistency Policy at 1 and 3 steps, OneDP's one-step generator;
* the peer's own path: the same network driven by diffusers' ``DDPMScheduler`` (100 steps) and
  ``DDIMScheduler`` (16 steps) in Diffusion Policy's loop (``scheduler.step(...).prev_sample``);
* the floor: the encoder and 2 UNet forwards timed alone (no normalisation, no sampler code).

Reported: median wall and process-CPU milliseconds, L1 Flow's overhead over the floor (goal
<= 1.05x), and speed-ups of L1 Flow over each method as ratios from this run. Training: one AdamW
step of each loss at batch 256, the distillation losses (Consistency Policy's trajectory objective,
OneDP-D, OneDP-S) with a frozen EDM teacher of the same network. Methods take turns within each
round, so drifting load hits them alike. ``--threads`` defaults to 1: on a busy 2-core machine
torch's intra-op threads spin-wait. The image network's training step is ``bench_image_train``'s
subject, so ``--network image`` times inference only.

    python -m benchmarks.speed.bench_latency [--quick] [--network state|mlp|image] [--out PATH]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable

import torch
from tensordict import TensorDict

from benchmarks.lib.common import format_table, interleaved, machine_info, parse_args, save_results
from l1flow_rl import (
    ConsistencyLoss,
    DiffusionLoss,
    EDMLoss,
    FlowMatchingLoss,
    L1FlowActor,
    L1FlowLoss,
    OneDPDLoss,
    OneDPSLoss,
    RegressionLoss,
)
from l1flow_rl.config import NetworkConfig, PolicyConfig
from l1flow_rl.workspace.build import build_actor as build_policy_actor

OBS_DIM, ACTION_DIM, TRAIN_BATCH = 35, 4, 256

#: method -> (sampler name, sampler options)
SAMPLERS: dict[str, tuple[str, dict]] = {
    "l1flow_2nfe": ("two_step", {"t_first": 0.5}),
    "euler1": ("euler", {"steps": 1}),
    "euler2": ("euler", {"steps": 2}),
    "euler5": ("euler", {"steps": 5}),
    "euler10": ("euler", {"steps": 10}),
    "vflow_euler10": ("velocity_euler", {"steps": 10}),
    "ddim16": ("ddim", {"steps": 16}),
    "ddpm100": ("ddpm", {}),
    "regression": ("direct", {}),
    "edm_heun18": ("edm_heun", {"steps": 18}),
    "edm_heun10": ("edm_heun", {"steps": 10}),
    "cp1": ("edm_consistency", {"steps": 1, "trajectory": True}),
    "cp3": ("edm_consistency", {"steps": 3, "trajectory": True}),
    "onedp1": ("onedp_edm", {"stochastic": True}),
}
#: method -> the loss that trains a network for it (DDIM trains like DDPM, Euler like L1 Flow)
TRAINED = {
    "l1flow_2nfe": L1FlowLoss,
    "vflow_euler10": FlowMatchingLoss,
    "ddpm100": DiffusionLoss,
    "regression": RegressionLoss,
    "edm_heun18": EDMLoss,
}
#: loss -> (its student's sampler, the loss's options): distilled from an EDM teacher (edm_heun18)
DISTILLED: dict[str, tuple[tuple[str, dict], Callable[..., object], dict]] = {
    "consistency": (SAMPLERS["cp1"], ConsistencyLoss, {"trajectory": True}),
    "onedp_d": (("onedp_edm", {"stochastic": False}), OneDPDLoss, {}),
    "onedp_s": (SAMPLERS["onedp1"], OneDPSLoss, {}),
}


IMAGE_TASK = "maniskill_pushcube_rgb"


def _image_setup(quick: bool = False) -> tuple[dict, dict, dict, dict]:
    """The image task's policy, encoder and network configs as the train job composes them, and its
    shapes."""
    from omegaconf import OmegaConf

    from benchmarks.speed.bench_image_latency import SIDE, STATE_DIM
    from l1flow_rl.commands.cli import compose_config

    overrides = [f"task={IMAGE_TASK}", "encoder=resnet18_gn"]
    cfg = compose_config([*overrides, *(["network.down_dims=[16,32]"] if quick else [])])
    policy, encoder, network = (
        OmegaConf.to_container(c, resolve=True) for c in (cfg.policy, cfg.encoder, cfg.network)
    )
    return policy, encoder, network, {"state": (STATE_DIM,), "rgb": (3, SIDE, SIDE)}


def _state_network(network: str) -> dict:
    """The state denoiser's settings: the train job's default (``state``: the UNet) or ``mlp``'s group."""
    if network == "mlp":
        from omegaconf import OmegaConf

        from l1flow_rl.commands.cli import compose_config

        return OmegaConf.to_container(compose_config(["network=mlp"], command="eval").network, resolve=True)
    return dataclasses.asdict(NetworkConfig())


def build_actor(
    method: str,
    device: torch.device,
    policy: PolicyConfig | None = None,
    network: str = "state",
    quick: bool = False,
    network_cfg: NetworkConfig | None = None,
    sampler: tuple[str, dict] | None = None,
) -> L1FlowActor:
    """The network as the train job builds it (state, ``mlp``, or the image task's), with ``method``'s
    sampler (or ``sampler``). ``policy`` and ``network_cfg`` (the state network's; default: the train
    job's defaults)."""
    name, options = sampler or SAMPLERS[method]
    if network == "image":
        cfg, encoder, net, shapes = _image_setup(quick)
        cfg = {**cfg, "sampler": name, "sampler_kwargs": options}
        return build_policy_actor(cfg, shapes, ACTION_DIM, encoder, net).to(device).eval()
    cfg = dataclasses.replace(policy or PolicyConfig(), sampler=name, sampler_kwargs=options)
    net = dataclasses.asdict(network_cfg) if network_cfg is not None else _state_network(network)
    return (
        build_policy_actor(dataclasses.asdict(cfg), {"state": (OBS_DIM,)}, ACTION_DIM, None, net)
        .to(device)
        .eval()
    )


def _observation(batch: int, device: torch.device, network: str = "state") -> TensorDict:
    if network == "image":
        from benchmarks.speed.bench_image_latency import observation

        return observation(batch, PolicyConfig().obs_horizon, device)
    return TensorDict(
        {"observation": torch.randn(batch, PolicyConfig().obs_horizon, OBS_DIM)}, [batch], device=device
    )


def _diffusers_call(actor: L1FlowActor, scheduler, steps: int, obs: TensorDict) -> Callable[[], None]:
    """Diffusion Policy's sampling loop with a diffusers scheduler, around the same network."""
    policy = actor.policy

    @torch.inference_mode()
    def call() -> None:
        o = policy.as_obs_dict(obs.get("observation"))
        cond = policy.encode(o)
        x = torch.randn(cond.shape[0], policy.pred_horizon, policy.action_dim, device=cond.device)
        scheduler.set_timesteps(steps)
        for t in scheduler.timesteps:
            eps = policy.net(x, t.to(cond.device).expand(x.shape[0]), cond)
            x = scheduler.step(eps, t, x).prev_sample
        policy.executable(policy.action_normalizer.unnormalize(x))

    return call


#: Diffusion Policy's scheduler settings, which DDPMSampler/DDIMSampler reproduce
DIFFUSERS_SCHEDULER_OPTIONS = {
    "num_train_timesteps": 100,
    "beta_schedule": "squaredcos_cap_v2",
    "clip_sample": True,
    "prediction_type": "epsilon",
}


def diffusers_calls(actor: L1FlowActor, obs: TensorDict) -> dict[str, Callable[[], None]]:
    """The peers' path: DDPM-100 and DDIM-16 through diffusers' schedulers around ``actor``'s network."""
    from diffusers import DDIMScheduler, DDPMScheduler

    return {
        "diffusers_ddpm100": _diffusers_call(actor, DDPMScheduler(**DIFFUSERS_SCHEDULER_OPTIONS), 100, obs),
        "diffusers_ddim16": _diffusers_call(actor, DDIMScheduler(**DIFFUSERS_SCHEDULER_OPTIONS), 16, obs),
    }


def _floor_call(actor: L1FlowActor, obs: TensorDict) -> Callable[[], None]:
    """The encoder and 2 UNet forwards alone: what any 2-NFE policy must pay."""
    policy = actor.policy

    @torch.inference_mode()
    def call() -> None:
        cond = policy.encoder(policy.as_obs_dict(obs.get("observation"))).flatten(1)
        x = torch.randn(cond.shape[0], policy.pred_horizon, policy.action_dim, device=cond.device)
        t = torch.zeros(cond.shape[0], device=cond.device)
        policy.net(policy.net(x, t, cond), t + 0.5, cond)

    return call


def inference_calls(
    device: torch.device, batch: int, peers: bool, network: str = "state", quick: bool = False
) -> dict[str, Callable[[], None]]:
    obs = _observation(batch, device, network)
    base = build_actor("l1flow_2nfe", device, network=network, quick=quick)
    calls: dict[str, Callable[[], None]] = {"floor_2_unet": _floor_call(base, obs)}
    for method in SAMPLERS:
        actor = build_actor(method, device, network=network, quick=quick)
        if method != "regression":  # regression's UNet has no timestep input: its own network
            # The same network object under each sampler (and under the floor and diffusers' loops):
            # with one call per method per round, separate copies of the weights would each start
            # cold in the CPU caches while the floor's stayed warm (batch 1: 1.45x over the floor with
            # copies, 1.03x shared). Regression's own network still starts cold here.
            for part in ("net", "encoder", "obs_normalizer", "action_normalizer"):
                setattr(actor.policy, part, getattr(base.policy, part))

        @torch.inference_mode()
        def call(actor=actor) -> None:
            actor(obs.clone() if network == "image" else obs)  # "action_chunk" lands in the input

        calls[method] = call
    if peers:
        calls.update(diffusers_calls(base, obs))
    return calls


def training_steps(device: torch.device, batch: int, network: str = "state") -> dict[str, Callable[[], None]]:
    p = PolicyConfig()
    data = TensorDict(
        {
            "observation": torch.randn(batch, p.obs_horizon, OBS_DIM),
            "action_chunk": torch.rand(batch, p.pred_horizon, ACTION_DIM) * 2 - 1,
        },
        [batch],
        device=device,
    )
    losses = {m: loss_cls(build_actor(m, device, network=network).train()) for m, loss_cls in TRAINED.items()}
    teacher = build_actor("edm_heun18", device, network=network)
    for name, (sampler, loss_cls, options) in DISTILLED.items():
        student = build_actor(name, device, network=network, sampler=sampler).train()
        losses[name] = loss_cls(student, teacher=teacher, **options)
    steps = {}
    for method, loss_fn in losses.items():
        params = [*loss_fn.actor_network.parameters(), *loss_fn.extra_parameters()]
        optim = torch.optim.AdamW(
            [q for q in params if q.requires_grad], lr=1e-4, betas=(0.95, 0.999), weight_decay=1e-6
        )

        def step(loss_fn=loss_fn, optim=optim) -> None:
            loss = loss_fn(data)[loss_fn.loss_name]
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()

        steps[method] = step
    return steps


def nfe_of(method: str) -> int:
    from l1flow_rl.flow.samplers import make_sampler

    name, options = SAMPLERS[method]
    return make_sampler(name, **options).nfe


def run(args: argparse.Namespace) -> dict:
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    torch.manual_seed(0)
    figures: dict = {"machine": machine_info(device), "quick": args.quick}
    actor = build_actor("l1flow_2nfe", device, network=args.network, quick=args.quick)
    net = _image_setup(args.quick)[2] if args.network == "image" else _state_network(args.network)
    figures["network"] = {
        "kind": args.network,
        "obs_dim": OBS_DIM if args.network != "image" else None,
        "action_dim": ACTION_DIM,
        "name": net["name"],
        **{k: list(net[k]) for k in ("down_dims", "hidden_dims") if net.get(k)},
        "parameters": sum(p.numel() for p in actor.parameters()),
    }
    if args.network == "image":
        figures["network"]["task"] = IMAGE_TASK
    figures["nfe"] = {m: nfe_of(m) for m in SAMPLERS} | {
        "floor_2_unet": 2,
        "diffusers_ddpm100": 100,
        "diffusers_ddim16": 16,
    }
    figures["inference"] = {}
    for batch in args.batches:
        calls = inference_calls(device, batch, not args.no_peers, args.network, args.quick)
        times = interleaved(calls, args.rounds, device)
        ref = times["l1flow_2nfe"]
        figures["inference"][f"batch{batch}"] = {
            "ms": {k: {m: round(v, 3) for m, v in r.items()} for k, r in times.items()},
            # > 1: the method is that many times slower than L1 Flow 2-NFE (wall time, this run)
            "slowdown_vs_l1flow": {k: round(r["wall_ms"] / ref["wall_ms"], 2) for k, r in times.items()},
            "l1flow_over_floor": round(ref["wall_ms"] / times["floor_2_unet"]["wall_ms"], 3),
            "l1flow_chunks_per_s": round(1e3 / ref["wall_ms"], 1),
        }
    if not args.no_train and args.network != "image":
        train = interleaved(training_steps(device, args.train_batch, args.network), args.train_rounds, device)
        figures["train_step_ms"] = {
            "batch": args.train_batch,
            "ms": {k: {m: round(v, 1) for m, v in r.items()} for k, r in train.items()},
        }
    figures["machine"]["load_average_1min_end"] = machine_info(device)["load_average_1min"]
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None, help="default: benchmarks/results/latency[_mlp|_image].json")
    parser.add_argument("--network", choices=("state", "mlp", "image"), default="state")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (0: torch's default)")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--train-batch", type=int, default=TRAIN_BATCH)
    parser.add_argument("--train-rounds", type=int, default=8)
    parser.add_argument("--no-train", action="store_true")
    parser.add_argument("--no-peers", action="store_true", help="skip diffusers' schedulers")
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not speed")
    args = parse_args(parser, argv)
    if args.quick:
        args.batches, args.rounds, args.train_batch, args.train_rounds = [1], 1, 8, 1
    if args.out is None:
        args.out = f"benchmarks/results/latency{'' if args.network == 'state' else '_' + args.network}.json"
    figures = run(args)
    save_results(args.out, figures)
    for name, block in figures["inference"].items():
        rows = [
            {
                "method": k,
                "nfe": figures["nfe"][k],
                "wall ms": v["wall_ms"],
                "cpu ms": v["cpu_ms"],
                "x L1 Flow": block["slowdown_vs_l1flow"][k],
            }
            for k, v in block["ms"].items()
        ]
        print(f"\nper-chunk latency, {name} ({figures['machine']['device']}):")
        print(format_table(rows, ["method", "nfe", "wall ms", "cpu ms", "x L1 Flow"]))
        print(f"L1 Flow over the floor (encoder + 2 UNet forwards): {block['l1flow_over_floor']}x")
    print(f"\nsaved {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
