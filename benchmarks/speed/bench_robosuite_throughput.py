"""Env steps per second through the robosuite adapter (make_env) against raw robosuite, same task.

Settings, each against its own raw baseline measured in this run:
  cpu_1env   raw: ``robosuite.make`` env stepped in this process; adapters: ``RobosuiteEnv`` (the
             unbatched env a worker runs) and ``make_env(num_envs=1)`` (SerialEnv + history stack);
  cpu_Nproc  raw: N robosuite envs in worker processes under gymnasium's ``AsyncVectorEnv``;
             adapter: ``make_env(num_envs=N)`` (TorchRL ParallelEnv workers + history stack).
Every side steps the same pre-drawn absolute OSC_POSE targets (the home pose plus noise) and
resets at the time limit. The adapter's step includes what it adds on purpose: ``forward()`` and
the observation recomputed at the new state. Raw and adapter blocks alternate (``--rounds``) and
medians are reported, so that load drifting on a shared machine hits all alike. ``--quick`` times
a few steps in 2 rounds to check the script end to end, and saves
``robosuite_throughput_<task>_quick.json`` unless ``--out`` says otherwise; it keeps ``--workers``
(2 by default), since ``make_env`` runs a single env in process and only 2 or more reach the workers.

    python -m benchmarks.speed.bench_robosuite_throughput [--task robosuite_lift] [--workers 2] [--quick]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
import torch

from benchmarks.lib.common import format_table, machine_info, parse_args, save_results
from l1flow_rl.config import TaskConfig, load_task_config

Stepper = tuple[Callable[[int], None], Callable[[], None]]
#: --quick: timed steps per env and side, rounds (2: the median over rounds), warm-up steps
QUICK_STEPS, QUICK_ROUNDS, QUICK_WARMUP = 4, 2, 1


def _raw_env(task: TaskConfig):
    from l1flow_rl.envs.robosuite import sim

    cameras = task.cameras if task.obs_mode == "rgb" else []
    return sim.make_from_env_args(sim.env_args_for_task(task, cameras=cameras, render=False))


def _home_actions(task: TaskConfig, steps: int, num_envs: int) -> np.ndarray:
    """Absolute targets around the robot's start pose (random absolute targets would fling the arm)."""
    from scipy.spatial.transform import Rotation

    from l1flow_rl.experts.robosuite.scripted import canonical_rotvec

    env = _raw_env(task)
    raw = env.reset()
    site = env.robots[0].eef_site_id["right"]
    home = np.concatenate(
        [
            raw["robot0_eef_pos"],
            canonical_rotvec(Rotation.from_matrix(env.sim.data.site_xmat[site].reshape(3, 3))),
            [0.0],
        ]
    )
    dim = env.action_dim
    env.close()
    rng = np.random.default_rng(0)
    actions = np.tile(np.resize(home, dim), (steps, num_envs, 1))
    actions[..., :3] += rng.uniform(-0.05, 0.05, (steps, num_envs, 3))
    actions[..., -1] = rng.choice([-1.0, 1.0], (steps, num_envs))
    return actions


def raw_in_process(task: TaskConfig, actions: np.ndarray) -> Stepper:
    env = _raw_env(task)
    env.reset()
    count = {"t": 0}

    def step(i: int) -> None:
        env.step(actions[i, 0])
        count["t"] += 1
        if count["t"] >= task.max_episode_steps:
            env.reset()
            count["t"] = 0

    return step, env.close


class _RawGym(gym.Env):
    """A raw robosuite env behind gymnasium's API, for the AsyncVectorEnv baseline."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, task: TaskConfig) -> None:
        torch.set_num_threads(1)
        self.env = _raw_env(task)
        obs = self.env.reset()
        self.keys = [k for k in obs if not k.endswith("_image")]
        dim = sum(np.size(obs[k]) for k in self.keys)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (dim,), np.float64)
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (self.env.action_dim,), np.float64)
        self.render_mode = None

    def _flat(self, obs) -> np.ndarray:
        return np.concatenate([np.ravel(obs[k]) for k in self.keys])

    def reset(self, *, seed=None, options=None):
        return self._flat(self.env.reset()), {}

    def step(self, action):
        obs, reward, _, _ = self.env.step(action)
        return self._flat(obs), float(reward), False, False, {}

    def close(self) -> None:
        self.env.close()


def raw_processes(task: TaskConfig, workers: int, actions: np.ndarray) -> Stepper:
    import functools

    from gymnasium.vector import AsyncVectorEnv, AutoresetMode
    from l1flow_rl.envs.robosuite.pool import forkserver

    env = AsyncVectorEnv(
        [functools.partial(_RawGym, task)] * workers,
        context=forkserver(),
        autoreset_mode=AutoresetMode.DISABLED,
    )
    env.reset(seed=0)
    count = {"t": 0}

    def step(i: int) -> None:
        env.step(actions[i])
        count["t"] += 1
        if count["t"] >= task.max_episode_steps:
            env.reset()
            count["t"] = 0

    return step, env.close


def adapter_unbatched(task: TaskConfig, actions: np.ndarray) -> Stepper:
    from l1flow_rl.envs.robosuite.env import RobosuiteEnv

    env = RobosuiteEnv(task, render=False)
    state = {"td": env.reset()}
    acts = torch.as_tensor(actions, dtype=torch.float32)

    def step(i: int) -> None:
        td = state["td"]
        td["action"] = acts[i, 0]
        _, state["td"] = env.step_and_maybe_reset(td)

    return step, env.close


def adapter(task: TaskConfig, num_envs: int, actions: np.ndarray) -> Stepper:
    from l1flow_rl.envs import make_env

    env = make_env(task, num_envs=num_envs, render=False)
    state = {"td": env.reset()}
    acts = torch.as_tensor(actions, dtype=torch.float32)

    def step(i: int) -> None:
        td = state["td"]
        td["action"] = acts[i]
        _, state["td"] = env.step_and_maybe_reset(td)

    return step, env.close


def measure(name: str, num_envs: int, sides: dict[str, Callable[[], Stepper]], args) -> dict:
    made = {side: make() for side, make in sides.items()}
    torch.set_num_threads(1)  # ParallelEnv resets this process's thread count when it starts
    block = args.steps // args.rounds
    rates: dict[str, list[float]] = {side: [] for side in made}
    try:
        for step, _ in made.values():
            for i in range(args.warmup):
                step(i)
        for r in range(args.rounds):
            first = args.warmup + r * block
            for side, (step, _) in made.items():
                start = time.perf_counter()
                for i in range(first, first + block):
                    step(i)
                rates[side].append(num_envs * block / (time.perf_counter() - start))
    finally:
        for _, close in made.values():
            close()
    raw = statistics.median(rates["raw"])
    row = {"setting": name, "num_envs": num_envs, "raw_steps_per_s": round(raw, 1)}
    for side in made:
        if side != "raw":
            ours = statistics.median(rates[side])
            row[f"{side}_steps_per_s"] = round(ours, 1)
            row[f"{side}_over_raw"] = round(ours / raw, 3)
    print(row, flush=True)
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="robosuite_lift")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--steps", type=int, default=300, help="timed steps per env and side")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument(
        "--out", default=None, help="default: benchmarks/results/robosuite_throughput_<task>[_quick].json"
    )
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not speed")
    args = parse_args(parser, argv)
    if args.quick:
        args.steps, args.rounds, args.warmup = QUICK_STEPS, QUICK_ROUNDS, QUICK_WARMUP
    torch.set_num_threads(1)
    task = load_task_config(args.task)
    total = args.warmup + args.steps
    one = _home_actions(task, total, 1)
    many = _home_actions(task, total, args.workers)
    rows = [
        measure(
            "cpu_1env",
            1,
            {
                "raw": lambda: raw_in_process(task, one),
                "unbatched": lambda: adapter_unbatched(task, one),
                "make_env": lambda: adapter(task, 1, one),
            },
            args,
        ),
        measure(
            f"cpu_{args.workers}proc",
            args.workers,
            {
                "raw": lambda: raw_processes(task, args.workers, many),
                "make_env": lambda: adapter(task, args.workers, many),
            },
            args,
        ),
    ]
    columns = sorted({k for r in rows for k in r}, key=lambda k: (k != "setting", k != "num_envs", k))
    print(format_table(rows, columns))
    result = {
        "quick": args.quick,
        "task": task.name,
        "env_id": task.env_id,
        "obs_mode": task.obs_mode,
        "cameras": task.cameras,
        "image_size": task.image_size,
        "timed_steps_per_env": args.steps,
        "rounds": args.rounds,
        "machine": machine_info(),
        "rows": rows,
    }
    default = f"benchmarks/results/robosuite_throughput_{task.name}{'_quick' if args.quick else ''}.json"
    out = save_results(args.out or default, result)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
