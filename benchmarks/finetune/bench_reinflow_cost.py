"""What ReinFlow's route (PPO over L1 Flow's 2-NFE chain with learned noise) would cost on this machine.

The fine-tuning issue's plan B. Before building a PPO loop, this prices its parts on the MLP policy
(``configs/network/mlp.yaml``, 4 x 512) at the task's sizes, all in one interleaved loop (one thread):

* acting: the noisy chain (:class:`~l1flow_rl.modules.noisy_chain.NoisyTwoStepChain`: 2 flow calls and
  2 calls of the noise MLP) against the plain 2-NFE chunk, at batch 1 and ``--envs``;
* ``ppo_minibatch``: one PPO minibatch of ``--batch`` chains: the chain's log-likelihood under the
  current weights, a value MLP (3 x 256), the clipped surrogate, backward and Adam;
* env: steps/s of raw ManiSkill (physx_cpu) in this process and in ``--envs`` worker processes.

From these, the hours one core spends per million env steps (env stepping, acting, and ``--epochs``
passes of PPO over every chunk decision), and how many env steps fit in 2 hours of 2 cores, beside
ReinFlow's published budgets (its robomimic curves: about 6M env steps on Can, 24M on Square).

    python -m benchmarks.finetune.bench_reinflow_cost [--task maniskill_pickcube] [--rounds 5]

``--quick`` runs every part once at a tiny batch, to check the script (not the speed).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch
from omegaconf import OmegaConf
from torch import nn

from benchmarks.finetune.bench_finetune_cost import state_sizes
from benchmarks.lib.common import interleaved, machine_info, parse_args, save_results
from benchmarks.speed.bench_env_throughput import measure, raw_in_process, raw_processes
from l1flow_rl.commands.cli import compose_config
from l1flow_rl.config import PolicyConfig, load_task_config
from l1flow_rl.modules.noisy_chain import NoisyTwoStepChain
from l1flow_rl.workspace.build import build_actor

#: ReinFlow's robomimic settings (references: its released configs and curves)
PPO = {"epochs": 10, "clip": 0.01, "value_hidden": [256, 256, 256]}
PUBLISHED_ENV_STEPS = {"robomimic_can": 6e6, "robomimic_square": 24e6}


def value_net(obs_numel: int) -> nn.Module:
    layers, width = [], obs_numel
    for h in PPO["value_hidden"]:
        layers += [nn.Linear(width, h), nn.Mish()]
        width = h
    return nn.Sequential(*layers, nn.Linear(width, 1))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="maniskill_pickcube")
    parser.add_argument("--batch", type=int, default=256, help="PPO minibatch (chains)")
    parser.add_argument("--envs", type=int, default=2, help="parallel envs (worker processes)")
    parser.add_argument("--epochs", type=int, default=PPO["epochs"])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--env-steps", type=int, default=400, help="timed env steps per side")
    parser.add_argument("--out", default=None)
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not speed")
    args = parse_args(parser, argv)
    if args.quick:
        args.batch, args.rounds, args.env_steps = 4, 1, 8
    torch.set_num_threads(1)
    task = load_task_config(args.task)
    obs_dim, action_dim = state_sizes(task)
    policy_cfg = dataclasses.asdict(PolicyConfig())
    network = OmegaConf.to_container(compose_config(["network=mlp"]).network, resolve=True)
    flow = build_actor(policy_cfg, {"state": (obs_dim,)}, action_dim, None, network)
    chain = NoisyTwoStepChain(flow.policy)
    to, h = policy_cfg["obs_horizon"], policy_cfg["action_steps"]
    value = value_net(to * obs_dim)
    optim = torch.optim.Adam([*chain.parameters(), *value.parameters()], lr=1e-5)
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(args.batch, to, obs_dim, generator=g)
    with torch.no_grad():
        stored = chain.sample(obs)
    advantages, returns = torch.randn(args.batch, generator=g), torch.randn(args.batch, generator=g)

    def ppo_minibatch() -> None:
        log_prob = chain.log_prob(obs, stored["x0"], stored["x_mid"], stored["chunk"])
        ratio = (log_prob - stored["log_prob"]).exp()
        clipped = ratio.clamp(1 - PPO["clip"], 1 + PPO["clip"])
        actor_loss = -torch.minimum(ratio * advantages, clipped * advantages).mean()
        value_loss = (value(obs.flatten(1)).squeeze(-1) - returns).square().mean()
        optim.zero_grad(set_to_none=True)
        (actor_loss + 0.5 * value_loss).backward()
        optim.step()

    fns = {"ppo_minibatch": ppo_minibatch}
    for n in sorted({1, args.envs}):
        o = obs[:n] if n <= args.batch else torch.randn(n, to, obs_dim, generator=g)
        fns[f"chunk_2nfe_b{n}"] = lambda o=o: torch.no_grad()(flow.policy.sample_chunk)(o)
        fns[f"chain_b{n}"] = lambda o=o: torch.no_grad()(chain.sample)(o)
    ms = {
        k: round(v["wall_ms"], 3)
        for k, v in interleaved(fns, rounds=args.rounds, device=torch.device("cpu")).items()
    }
    print(ms, flush=True)

    cpu = torch.device("cpu")
    actions = torch.rand(30 + args.env_steps, max(args.envs, 1), action_dim, generator=g) * 2 - 1
    env_args = argparse.Namespace(
        steps=args.env_steps, rounds=max(args.rounds, 2), warmup=2 if args.quick else 30, threads=1
    )
    one = measure("cpu_1env", lambda: raw_in_process(task, cpu, 1, actions[:, :1]), {}, 1, cpu, env_args)
    workers = measure(
        f"cpu_{args.envs}workers",
        lambda: raw_processes(task, args.envs, actions),
        {},
        args.envs,
        cpu,
        env_args,
    )

    # one core's seconds per env step: stepping, acting (a chain per h steps, batched over the envs),
    # and PPO (every chunk decision passes `epochs` times through a minibatch)
    step_s = 1.0 / one["raw_steps_per_s"]
    act_s = ms[f"chain_b{args.envs}"] / 1e3 / (h * args.envs)
    ppo_s = args.epochs * ms["ppo_minibatch"] / 1e3 / (args.batch * h)
    per_step = {"env": step_s, "acting": act_s, "ppo": ppo_s}
    core_hours_per_million = {k: round(v * 1e6 / 3600, 3) for k, v in per_step.items()}
    total = sum(per_step.values())
    fit_2h_2cores = 2 * 2 * 3600 / total  # both cores busy, no overhead: an upper bound
    result = {
        "task": task.name,
        "obs_dim": obs_dim,
        "action_dim": action_dim,
        "network": network["name"],
        "network_dims": network["hidden_dims"],
        "batch": args.batch,
        "envs": args.envs,
        "epochs": args.epochs,
        "executed_per_chunk": h,
        "ppo": PPO,
        "quick": args.quick,
        "machine": machine_info("cpu"),
        "wall_ms": ms,
        "ratios": {
            f"chain_over_2nfe_b{n}": round(ms[f"chain_b{n}"] / ms[f"chunk_2nfe_b{n}"], 3)
            for n in sorted({1, args.envs})
        },
        "env": {"in_process": one, "workers": workers},
        "core_hours_per_million_env_steps": {**core_hours_per_million, "total": round(total * 1e6 / 3600, 3)},
        "env_steps_in_2h_of_2_cores_at_most": round(fit_2h_2cores),
        "published_env_steps": PUBLISHED_ENV_STEPS,
        "hours_of_2_cores_for_published": {
            k: round(v * total / 2 / 3600, 1) for k, v in PUBLISHED_ENV_STEPS.items()
        },
    }
    headline = ("ratios", "core_hours_per_million_env_steps", "env_steps_in_2h_of_2_cores_at_most")
    print({k: result[k] for k in headline})
    name = f"reinflow_cost_{task.name}_mlp{'_quick' * args.quick}.json"
    print(f"wrote {save_results(Path(args.out or f'benchmarks/results/{name}'), result)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
