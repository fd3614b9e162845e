"""Where a fine-tuning update's time goes on this machine, and what acting costs the env loop.

For QC, FQL, flow-Q, DSRL and DSRL-NA (their presets, ``configs/finetune/``) at batch 256 with the
policy network ``--network`` (``configs/network/``: ``unet``, the ManiSkill-sized UNet, down_dims
64/128/256, or ``mlp``, 4 x 512) on the task's observation and action sizes, the parts of one update
of every setting are timed in alternation, all settings in one loop
(``benchmarks.lib.common.interleaved``):

* ``targets``: the TD target (QC: N proposals at s' by the 2-NFE sampler, the online critics' pick,
  the target critics' value; FQL: mu at s'; DSRL: the noise actor at s'), and within it
  ``proposals_2nfe`` (QC: the flow on 256 x N chunks) alone; DSRL-NA: the actor's w' decoded at s';
* ``critic_fwd_bwd``: the critics' regression onto a fixed target, forward and backward;
* ``actor_fwd_bwd``: FQL's mu loss (with its 2-NFE teacher), flow-Q's actor loss (the actor's 2-NFE
  chunk with its gradient, the teacher's, the critics), DSRL's noise-actor and temperature losses;
* ``distill_fwd_bwd``: DSRL-NA's noise critic fitted to the action critic (cached chunks: timed warm);
* ``bc_fwd_bwd``: the flow's L1 Flow loss (QC, FQL);
* ``update``: the whole update as the loop runs it (losses, backward, Adam, SoftUpdate).

Variants that bear on design choices: QC with N = 8, QC with the flow frozen (its proposals cached per
next observation: timed warm, as in a run where each stored state's proposals were drawn once, with
``proposals_2nfe`` the one-time cost of 256 observations' draws), critics of 2 x 256.
Then env steps/s of one physx_cpu env stepping random actions (raw) against the env driven by each
algorithm's acting module (one chunk per 8 steps). Ratios are against baselines of the same run.

    python -m benchmarks.finetune.bench_finetune_cost [--task maniskill_pickcube] [--network mlp] \\
        [--rounds 5] [--threads 2]

``--quick`` runs every part once at a tiny batch, to check the script (not the speed).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch
from omegaconf import OmegaConf, open_dict
from tensordict import TensorDict
from torchrl.objectives import SoftUpdate

from benchmarks.lib.common import format_table, interleaved, machine_info, parse_args, save_results
from benchmarks.speed.bench_env_throughput import measure, policy_in_loop, raw_in_process
from l1flow_rl.commands.cli import compose_config
from l1flow_rl.config import PolicyConfig, load_task_config
from l1flow_rl.finetune.registry import get_algorithm
from l1flow_rl.workspace.build import build_actor

#: what each figure motivated (kept in the JSON beside the figures)
DESIGN = {
    "qc_proposals_share_of_update": (
        "QC's update is the flow on 256 x N proposals: the critics and targets are small beside it; the "
        "online runs here use N=8 and 1 update per 20 env steps (bench_finetune_online.CPU_BUDGET)"
    ),
    "qc_frozen_flow_over_qc_update": (
        "with the flow frozen, each observation's N proposals are drawn once (ProposalCache): a warm "
        "update costs the critics' pick over 256 x N cached chunks, not the flow; before the cache, "
        "freezing saved only the BC term (0.43x)"
    ),
    "qc_critic_2x256_over_qc_update": "smaller critics do not change QC's cost (the proposals dominate)",
    "fql_over_qc_update": (
        "FQL costs its BC term and one 2-NFE teacher call at batch 256: 1 update per 4 env steps here"
    ),
    "dsrl_over_qc_update": (
        "DSRL's update never calls the flow (its critic is Q(s, w)): the plain variant keeps the "
        "preset's UTD 1"
    ),
    "dsrl_critic_2x256_over_dsrl_update": "DSRL's remaining cost is its MLPs: 2 x 256 critics halve it",
    "dsrl_na_over_dsrl_update": (
        "DSRL-NA's bootstrap decodes the actor's w' at every next state (one 2-NFE call at the batch); its "
        "distillation's chunks are cached per state (timed warm): the online runs here take batch 128"
    ),
    "env": "acting: QC's 32 proposals per chunk cost most (0.29x raw), FQL's one MLP call least (0.79x)",
}
#: what the MLP policy's figures decided (the budgets of the MLP starts' runs, bench_finetune_online)
MLP_DESIGN: dict[str, str] = {
    "flowq_over_fql_update": (
        "flow-Q's update (the actor through both NFEs, the frozen teacher's chunk, the critics) costs "
        "FQL's: the 2-NFE flow as its own actor saves FQL's distillation of mu, not compute per update"
    ),
    "fql_over_qc_update": (
        "on the MLP the critics (4 x 512) are a quarter of an FQL or flow-Q update: at 0.5 updates per "
        "env step, 100k env steps with 10k offline updates first cost about 3 hours of one core"
    ),
}


def state_sizes(task) -> tuple[int, int]:
    """(observation size, action size) of a ManiSkill state task, read from one env."""
    from l1flow_rl.envs.maniskill.env import make_gym_env

    probe = make_gym_env(task, 1, torch.device("cpu"), render=False)
    try:
        return int(probe.unwrapped.single_observation_space.shape[-1]), int(
            probe.unwrapped.single_action_space.shape[0]
        )
    finally:
        probe.close()


def make_batch(batch: int, obs_dim: int, action_dim: int, policy: dict) -> TensorDict:
    to, horizon = policy["obs_horizon"], policy["pred_horizon"]
    g = torch.Generator().manual_seed(0)
    return TensorDict(
        {
            "observation": torch.randn(batch, to, obs_dim, generator=g),
            "action_chunk": torch.rand(batch, horizon, action_dim, generator=g) * 2 - 1,
            "noise": torch.rand(batch, horizon, action_dim, generator=g) * 3 - 1.5,
            "chunk_valid": torch.ones(batch, 1, dtype=torch.bool),
            "next": {
                "observation": torch.randn(batch, to, obs_dim, generator=g),
                "reward": torch.rand(batch, 1, generator=g),
                "terminated": torch.zeros(batch, 1, dtype=torch.bool),
            },
        },
        batch_size=[batch],
    )


def build_loss(algorithm: str, flow, overrides: list[str]):
    cfg = compose_config([f"finetune={algorithm}", *overrides], command="finetune")
    alg = get_algorithm(algorithm)
    with open_dict(cfg):  # the algorithm's block over its defaults, as the fine-tuning job fills it
        cfg.finetune[alg.name] = alg.settings_of(cfg.finetune)
    return alg.build(flow, cfg.finetune), cfg.finetune


def parts(loss, data: TensorDict) -> dict:
    """The timed callables of one update of ``loss`` on ``data``."""
    params = [p for p in loss.parameters() if p.requires_grad]
    optim = torch.optim.Adam(params, lr=3e-4)
    updater = SoftUpdate(loss, tau=0.005)
    obs = loss.read_observation(data, "observation")
    target = loss.td_target(data)

    def critic_fwd_bwd():
        q = loss.q(obs, loss.critic_input(data))
        (q - target.unsqueeze(-1)).square().mean().backward()

    def update():
        out = loss(data)
        optim.zero_grad(set_to_none=True)
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        optim.step()
        updater.step()

    fns = {"targets": lambda: loss.td_target(data), "critic_fwd_bwd": critic_fwd_bwd, "update": update}
    next_obs = loss.read_observation(data, ("next", "observation"))
    if type(loss).__name__ == "QCLoss":
        fns["proposals_2nfe"] = lambda: torch.no_grad()(loss.actor.propose)(next_obs)
    if hasattr(loss, "actor_loss"):

        def actor_fwd_bwd():
            out = loss.actor_loss(data)
            sum(v for v in out if isinstance(v, torch.Tensor) and v.requires_grad).backward()

        fns["actor_fwd_bwd"] = actor_fwd_bwd
    if hasattr(loss, "distill_loss"):
        loss.distill_loss(data)  # each state's chunks decoded once: the timed calls are warm, as in a run
        fns["distill_fwd_bwd"] = lambda: loss.distill_loss(data)[0].backward()
    if getattr(loss, "bc_loss", None) is not None:
        fns["bc_fwd_bwd"] = lambda: loss.bc_loss(data)[loss.bc_loss.loss_name].backward()
    return fns


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="maniskill_pickcube")
    parser.add_argument("--network", default="unet", help="a configs/network/ name: unet | mlp")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--env-steps", type=int, default=400, help="timed env steps per side")
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (1: the machine runs two experiments at once)"
    )
    parser.add_argument("--out", default=None)
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not speed")
    args = parse_args(parser, argv)
    if args.quick:
        args.batch, args.rounds, args.env_steps = 4, 1, 4
    torch.set_num_threads(args.threads)
    task = load_task_config(args.task)
    obs_dim, action_dim = state_sizes(task)
    policy = dataclasses.asdict(PolicyConfig())
    network = OmegaConf.to_container(compose_config([f"network={args.network}"]).network, resolve=True)
    data = make_batch(args.batch, obs_dim, action_dim, policy)
    small = ["finetune.critic_hidden_dims=[256,256]"]
    settings = {
        "qc": ("qc", []),
        "qc_n8": ("qc", ["finetune.qc.num_samples=8"]),
        "qc_frozen_flow": ("qc", ["finetune.qc.freeze_flow=true"]),
        "qc_critic_2x256": ("qc", small),
        "fql": ("fql", []),
        "flowq": ("flowq", []),
        "flowq_critic_2x256": ("flowq", small),
        "dsrl": ("dsrl", []),
        "dsrl_critic_2x256": ("dsrl", small),
        "dsrl_na": ("dsrl_na", []),
    }
    # every setting's parts take turns in one interleaved loop, so that load drifting on the shared
    # machine hits the settings alike and the ratios between settings stay fair
    fns = {}
    for name, (algorithm, overrides) in settings.items():
        flow = build_actor(policy, {"state": (obs_dim,)}, action_dim, None, network)
        loss, _ = build_loss(algorithm, flow, overrides)
        fns.update({f"{name}/{part}": fn for part, fn in parts(loss, data).items()})
    ms = interleaved(fns, rounds=args.rounds, device=torch.device("cpu"))
    timings = {name: {} for name in settings}
    for key, v in ms.items():
        name, part = key.split("/")
        timings[name][part] = round(v["wall_ms"], 2)
    rows = [{"setting": name, **t} for name, t in timings.items()]
    for name, t in timings.items():
        print(f"{name}: {t}", flush=True)
    print(
        format_table(
            rows,
            [
                "setting",
                "update",
                "targets",
                "proposals_2nfe",
                "critic_fwd_bwd",
                "actor_fwd_bwd",
                "bc_fwd_bwd",
                "distill_fwd_bwd",
            ],
        )
    )

    # env stepping: raw against each algorithm's acting module (one 2-NFE flow call per chunk, QC: at N)
    cpu = torch.device("cpu")
    actions = (
        torch.rand(30 + args.env_steps, 1, action_dim, generator=torch.Generator().manual_seed(0)) * 2 - 1
    )

    def acting(algorithm: str):
        return lambda flow: build_loss(algorithm, flow, [])[0].actor

    env_args = argparse.Namespace(
        steps=args.env_steps, rounds=max(args.rounds, 2), warmup=2 if args.quick else 30, threads=args.threads
    )
    env_row = measure(
        "cpu_1env",
        lambda: raw_in_process(task, cpu, 1, actions),
        {
            "bc_l1flow": lambda: policy_in_loop(task, cpu, 1),
            **{
                f"{a}_actor": (lambda a=a: policy_in_loop(task, cpu, 1, wrap=acting(a)))
                for a in ("qc", "fql", "flowq", "dsrl")
            },
        },
        1,
        cpu,
        env_args,
    )

    def ratio(a: str, b: str, part: str = "update") -> float:
        return round(timings[a][part] / timings[b][part], 3)

    qc = timings["qc"]
    result = {
        "task": task.name,
        "obs_dim": obs_dim,
        "action_dim": action_dim,
        "network": network["name"],
        "network_dims": network["down_dims"] or network["hidden_dims"],
        "batch": args.batch,
        "threads": args.threads,
        "rounds": args.rounds,
        "quick": args.quick,
        "machine": machine_info("cpu"),
        "wall_ms": timings,
        "ratios": {
            "qc_proposals_share_of_update": round(qc["proposals_2nfe"] / qc["update"], 3),
            "qc_targets_share_of_update": round(qc["targets"] / qc["update"], 3),
            "qc_n8_over_qc_update": ratio("qc_n8", "qc"),
            "qc_frozen_flow_over_qc_update": ratio("qc_frozen_flow", "qc"),
            "qc_critic_2x256_over_qc_update": ratio("qc_critic_2x256", "qc"),
            "fql_over_qc_update": ratio("fql", "qc"),
            "flowq_over_fql_update": ratio("flowq", "fql"),
            "flowq_critic_2x256_over_flowq_update": ratio("flowq_critic_2x256", "flowq"),
            "dsrl_over_qc_update": ratio("dsrl", "qc"),
            "dsrl_critic_2x256_over_dsrl_update": ratio("dsrl_critic_2x256", "dsrl"),
            "dsrl_na_over_dsrl_update": ratio("dsrl_na", "dsrl"),
        },
        "updates_per_s": {k: round(1e3 / v["update"], 2) for k, v in timings.items()},
        "design": DESIGN if args.network == "unet" else MLP_DESIGN,
        "env": env_row,
    }
    print(result["ratios"])
    suffix = ("" if args.network == "unet" else f"_{args.network}") + (
        "" if args.threads == 1 else f"_threads{args.threads}"
    )
    out = Path(
        args.out or f"benchmarks/results/finetune_cost_{task.name}{suffix}{'_quick' * args.quick}.json"
    )
    save_results(out, result)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
