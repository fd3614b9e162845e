"""The point mass's scripted expert: a PD controller, recorded as a robomimic-layout ``.hdf5``
(``data/demo_<i>/{obs/state, next_obs/state, actions, rewards, dones}``) that
:func:`l1flow_rl.data.load_episodes` reads."""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import torch
from torchrl.envs.utils import step_mdp

from l1flow_rl.config import TaskConfig
from l1flow_rl.experts import DemoGenerationError

from .env import PointMassEnv, expert_action

__all__ = ["make_point_mass_demos"]


def _episode(env: PointMassEnv, seed: int) -> dict[str, torch.Tensor] | None:
    """One expert episode from ``seed``, ending at success; None if the time limit came first."""
    td = env.reset(seed=[seed])
    obs, next_obs, actions, rewards = [], [], [], []
    while True:
        td["action"] = expert_action(td["observation"])
        td = env.step(td)
        obs.append(td["observation"][0])
        actions.append(td["action"][0])
        next_obs.append(td["next", "observation"][0])
        rewards.append(td["next", "reward"][0, 0])
        if td["next", "done"].item():
            if not td["next", "terminated"].item():
                return None
            break
        td = step_mdp(td)
    return {
        "obs": torch.stack(obs),
        "next_obs": torch.stack(next_obs),
        "actions": torch.stack(actions),
        "rewards": torch.stack(rewards),
    }


def make_point_mass_demos(task: TaskConfig, num: int, data_dir: str | os.PathLike, *, seed: int = 0) -> Path:
    """``num`` successful demonstrations of ``task`` from seeds ``seed, seed + 1, ...`` (a failed
    seed is skipped), written once under ``data_dir/point_mass/``; an existing file is reused."""
    path = Path(data_dir) / "point_mass" / f"{task.env_id}_{task.reward_mode}_seed{seed}_n{num}.hdf5"
    if path.is_file():
        return path
    env = PointMassEnv(task, num_envs=1, ignore_terminations=False, render=False)
    episodes, next_seed = [], seed
    while len(episodes) < num:
        if next_seed - seed >= 2 * num + 10:
            raise DemoGenerationError(
                f"point_mass expert: only {len(episodes)} of {num} episodes succeeded in "
                f"{next_seed - seed} tries (max_episode_steps={task.max_episode_steps})"
            )
        episode = _episode(env, next_seed)
        next_seed += 1
        if episode is not None:
            episodes.append(episode)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    with h5py.File(tmp, "w") as f:
        data = f.create_group("data")
        env_args = {"env_name": task.env_id, "type": "point_mass", "env_kwargs": {"mode": task.control_mode}}
        data.attrs["env_args"] = json.dumps(env_args)
        data.attrs["total"] = sum(len(e["actions"]) for e in episodes)
        for i, episode in enumerate(episodes):
            group = data.create_group(f"demo_{i}")
            group.attrs["num_samples"] = len(episode["actions"])
            group.create_dataset("obs/state", data=episode["obs"].numpy())
            group.create_dataset("next_obs/state", data=episode["next_obs"].numpy())
            group.create_dataset("actions", data=episode["actions"].numpy())
            group.create_dataset("rewards", data=episode["rewards"].numpy())
            dones = torch.zeros(len(episode["actions"]), dtype=torch.int64)
            dones[-1] = 1  # every kept episode ended in success
            group.create_dataset("dones", data=dones.numpy())
    os.replace(tmp, path)  # a half-written file never carries the final name
    return path
