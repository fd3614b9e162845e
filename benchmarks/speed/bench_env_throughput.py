"""Env steps per second through the TorchRL adapter (make_env) against raw ManiSkill, same task.

Three settings, each measured in this run against its own raw baseline:
  cpu_1env   one physx_cpu env in this process (raw: the gymnasium env stepped directly);
  cpu_2proc  two physx_cpu envs in worker processes (raw: gymnasium AsyncVectorEnv over ManiSkill's
             CPUGymWrapper, autoreset disabled), through both of make_env's CPU backends: "async"
             (the default, ManiSkillAsyncEnv) and "parallel" (TorchRL's ParallelEnv);
  gpu_<N>env one physx_cuda scene of N envs (skipped, with a note, when CUDA is absent).
In cpu_1env and gpu_<N>env a further side, ``l1flow_policy``, runs the adapter with an L1 Flow actor
choosing the actions (one 2-NFE chunk per 8 steps, as evaluation runs), against the same raw baseline.
All sides step the same pre-drawn random actions and reset at the time limit; the adapters run
with their history stacking (the env the evaluator uses). Start-up is not timed. Raw and adapter
blocks alternate (``--rounds``) and the medians are reported, so that load drifting on a shared
machine hits all alike; this process's CPU time per step is reported too.

    python -m benchmarks.speed.bench_env_throughput [--steps 600] [--gpu-envs 256 1024] [--obs-mode rgb]

``--quick`` runs every setting for a few steps and rounds, to check the script (not the speed).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from l1flow_rl.envs import make_env
from l1flow_rl.envs.maniskill.env import make_gym_env

from benchmarks.lib.common import machine_info, parse_args, save_results
from l1flow_rl.config import TaskConfig, load_task_config

#: a prepared env: step(i) runs pre-drawn action i (resetting at the time limit); close()
Stepper = tuple[Callable[[int], None], Callable[[], None]]


def raw_in_process(task: TaskConfig, device: torch.device, num_envs: int, actions: torch.Tensor) -> Stepper:
    """Raw ManiSkill in this process: gym step on batched torch actions, full reset at the limit."""
    env = make_gym_env(task, num_envs, device)
    env.reset(seed=0)
    actions = actions.to(device)

    def step(i: int) -> None:
        _, _, _, truncated, _ = env.step(actions[i])
        if bool(truncated.any()):  # every env hits the limit at the same step
            env.reset()

    return step, env.close


def _cpu_gym_env(task: TaskConfig):
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    return CPUGymWrapper(make_gym_env(task, 1, torch.device("cpu")))


def raw_processes(task: TaskConfig, workers: int, actions: torch.Tensor) -> Stepper:
    """Raw ManiSkill in worker processes: gymnasium's AsyncVectorEnv (ManiSkill's ``SAME_STEP``
    autoreset breaks on its reset info, so autoreset is off and resets are explicit)."""
    from gymnasium.vector import AsyncVectorEnv, AutoresetMode

    env = AsyncVectorEnv(
        [functools.partial(_cpu_gym_env, task)] * workers,
        context="forkserver",
        autoreset_mode=AutoresetMode.DISABLED,
    )
    env.reset(seed=0)
    actions = actions.numpy()

    def step(i: int) -> None:
        _, _, _, truncated, _ = env.step(actions[i])
        if truncated.any():
            env.reset()

    return step, env.close


def adapter(
    task: TaskConfig, device: torch.device, num_envs: int, actions: torch.Tensor, **make_kwargs
) -> Stepper:
    """make_env's TorchRL env, stepped with step_and_maybe_reset (resets each done env)."""
    env = make_env(task, num_envs=num_envs, device=device, **make_kwargs)
    state = {"td": env.reset()}
    actions = actions.to(env.device)

    def step(i: int) -> None:
        td = state["td"]
        td["action"] = actions[i]
        _, state["td"] = env.step_and_maybe_reset(td)

    return step, env.close


def policy_in_loop(
    task: TaskConfig, device: torch.device, num_envs: int, wrap: Callable | None = None, **make_kwargs
) -> Stepper:
    """make_env's env driven by an L1 Flow actor of the task's default network (PolicyConfig and
    NetworkConfig; the weights do not change the time) under TorchRL's ``MultiStepActorWrapper``, as
    the evaluator runs it: one 2-NFE chunk per ``action_steps`` env steps, re-planned where an env
    resets. The raw side it is compared with steps random actions, so the ratio prices the policy and
    the adapter together.
    ``wrap(actor)``: the module that acts instead (a fine-tuning algorithm's actor around the flow)."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type
    from torchrl.modules import MultiStepActorWrapper

    from l1flow_rl.config import NetworkConfig, PolicyConfig
    from l1flow_rl.workspace.build import build_actor

    env = make_env(task, num_envs=num_envs, device=device, **make_kwargs)
    td = env.reset()
    obs = td["observation"]
    per_step = len(td.batch_size) + 1  # after the env batch and the history dimension
    shapes = (
        {"state": tuple(obs.shape[per_step:])}
        if isinstance(obs, torch.Tensor)
        else {k: tuple(v.shape[per_step:]) for k, v in obs.items()}
    )
    policy = dataclasses.asdict(PolicyConfig())
    network = dataclasses.asdict(NetworkConfig())
    actor = build_actor(policy, shapes, env.action_spec.shape[-1], None, network).to(device).eval()
    if wrap is not None:
        actor = wrap(actor).to(device).eval()
    executor = MultiStepActorWrapper(actor, n_steps=policy["action_steps"], init_key="is_init")
    state = {"td": td}

    def step(i: int) -> None:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            _, state["td"] = env.step_and_maybe_reset(executor(state["td"]))

    return step, env.close


def _timed_block(
    step: Callable[[int], None], first: int, count: int, device: torch.device
) -> tuple[float, float]:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    wall, cpu = time.perf_counter(), time.process_time()
    for i in range(first, first + count):
        step(i)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - wall, time.process_time() - cpu


def measure(
    name: str, make_raw, adapters: dict[str, Callable[[], Stepper]], num_envs: int, device, args
) -> dict:
    """Steps/s of raw ManiSkill and of each adapter, in alternating blocks; ratios against raw."""
    sides = {"raw": make_raw(), **{side: make() for side, make in adapters.items()}}
    if args.threads > 0:  # TorchRL's ParallelEnv resets this process's thread count when it starts
        torch.set_num_threads(args.threads)
    threads = torch.get_num_threads()  # what the timed loops run with (closing a ParallelEnv resets it)
    block = args.steps // args.rounds
    rates: dict[str, list[float]] = {side: [] for side in sides}
    cpu_ms: dict[str, list[float]] = {side: [] for side in sides}
    try:
        for step, _ in sides.values():
            _timed_block(step, 0, args.warmup, device)
        for r in range(args.rounds):
            first = args.warmup + r * block
            for side, (step, _) in sides.items():
                wall, cpu = _timed_block(step, first, block, device)
                rates[side].append(num_envs * block / wall)
                cpu_ms[side].append(cpu / block * 1e3)
    finally:
        for _, close in sides.values():
            close()
    raw = statistics.median(rates["raw"])
    row = {
        "setting": name,
        "num_envs": num_envs,
        "raw_steps_per_s": round(raw, 1),
        "raw_main_process_cpu_ms_per_step": round(statistics.median(cpu_ms["raw"]), 3),
        "adapters": {},
        "torch_threads": threads,
    }
    line = f"{name:>12}: raw {raw:9.1f} steps/s ({row['raw_main_process_cpu_ms_per_step']:.2f} ms CPU here)"
    for side in adapters:
        ours = statistics.median(rates[side])
        row["adapters"][side] = {
            "steps_per_s": round(ours, 1),
            "over_raw": round(ours / raw, 3),
            "main_process_cpu_ms_per_step": round(statistics.median(cpu_ms[side]), 3),
        }
        line += (
            f" | {side} {ours:9.1f} steps/s, ratio {ours / raw:.3f}, {statistics.median(cpu_ms[side]):.2f} ms"
        )
    print(line, flush=True)
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="maniskill_pushcube")
    parser.add_argument("--obs-mode", default=None, help="override the task's obs_mode (state | rgb)")
    parser.add_argument("--steps", type=int, default=600, help="timed steps per env and side, after warm-up")
    parser.add_argument("--rounds", type=int, default=6, help="alternating raw/adapter blocks")
    parser.add_argument("--warmup", type=int, default=30)
    parser.add_argument("--gpu-envs", type=int, nargs="*", default=[256, 1024, 4096])
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads here (workers use 1); 0 keeps torch's default"
    )
    parser.add_argument(
        "--out", default=None, help="default: benchmarks/results/env_throughput_<obs>[_quick].json"
    )
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not speed")
    args = parse_args(parser, argv)
    if args.quick:
        args.steps, args.rounds, args.warmup, args.gpu_envs = 4, 2, 2, args.gpu_envs[:1]
    if args.threads > 0:  # on a loaded 2-core machine, 2 OpenMP threads make small tensor ops ~20x slower
        torch.set_num_threads(args.threads)
    task = load_task_config(args.task, **({"obs_mode": args.obs_mode} if args.obs_mode else {}))
    probe = make_gym_env(task, 1, torch.device("cpu"), render=False)
    action_dim = probe.unwrapped.single_action_space.shape[0]
    probe.close()
    generator = torch.Generator().manual_seed(0)

    def draw(num_envs: int) -> torch.Tensor:
        return torch.rand((args.warmup + args.steps, num_envs, action_dim), generator=generator) * 2 - 1

    cpu = torch.device("cpu")
    one, two = draw(1), draw(2)
    rows = [
        measure(
            "cpu_1env",
            lambda: raw_in_process(task, cpu, 1, one),
            {
                "in_process": lambda: adapter(task, cpu, 1, one),
                "l1flow_policy": lambda: policy_in_loop(task, cpu, 1),
            },
            1,
            cpu,
            args,
        ),
        measure(
            "cpu_2proc",
            lambda: raw_processes(task, 2, two),
            {
                backend: functools.partial(adapter, task, cpu, 2, two, cpu_backend=backend)
                for backend in ("async", "parallel")
            },
            2,
            cpu,
            args,
        ),
    ]
    notes = []
    if torch.cuda.is_available():
        gpu = torch.device("cuda")
        for n in args.gpu_envs:
            acts = draw(n)
            rows.append(
                measure(
                    f"gpu_{n}env",
                    lambda n=n, acts=acts: raw_in_process(task, gpu, n, acts),
                    {
                        "physx_cuda": lambda n=n, acts=acts: adapter(task, gpu, n, acts),
                        "l1flow_policy": lambda n=n: policy_in_loop(task, gpu, n),
                    },
                    n,
                    gpu,
                    args,
                )
            )
    else:
        notes.append("no CUDA device: GPU-parallel (physx_cuda) settings skipped")
        print(notes[-1])
    result = {
        "task": task.name,
        "env_id": task.env_id,
        "obs_mode": task.obs_mode,
        "control_mode": task.control_mode,
        "max_episode_steps": task.max_episode_steps,
        "timed_steps_per_env": args.steps,
        "rounds": args.rounds,
        "quick": args.quick,
        "machine": machine_info("cuda" if torch.cuda.is_available() else "cpu"),
        "rows": rows,
        "notes": notes,
    }
    out = Path(args.out or f"benchmarks/results/env_throughput_{task.obs_mode}{'_quick' * args.quick}.json")
    save_results(out, result)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
