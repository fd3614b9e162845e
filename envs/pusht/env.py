"""One gym-pusht env as a TorchRL env (batch size ``[]``); ``make_pusht_env`` runs several in worker
processes. Hand-written rather than ``GymWrapper`` + transforms: Diffusion Policy's keypoint
observation is computed from the block pose, and the contract's keys (``success``, ``coverage``,
flat or named observations) would otherwise need a chain of renaming and info-reading transforms."""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import torch
from l1flow_rl.envs.pusht.geometry import block_keypoints
from l1flow_rl.envs.registry import check_task_simulator
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from l1flow_rl.config import TaskConfig

__all__ = ["OBS_MODES", "PushTEnv", "observation_dim"]

#: TaskConfig.obs_mode -> gym-pusht's obs_type it reads. ``keypoints`` is Diffusion Policy's low-dim
#: observation (its 9 block keypoints, then the agent position: 20-D); ``environment_state_agent_pos``
#: is gym-pusht's / LeRobot's (the T's 8 corners, then the agent position: 18-D).
OBS_MODES = {
    "state": "state",
    "keypoints": "state",
    "environment_state_agent_pos": "environment_state_agent_pos",
    "pixels": "pixels",
    "pixels_agent_pos": "pixels_agent_pos",
}
IMAGE_MODES = ("pixels", "pixels_agent_pos")


def observation_dim(obs_mode: str) -> int:
    """The size of the flat (or ``"state"``) observation of a low-dim mode; 2 for pixels_agent_pos."""
    return {"state": 5, "keypoints": 20, "environment_state_agent_pos": 18, "pixels_agent_pos": 2}[obs_mode]


def _make_gym_env(task: TaskConfig, render: bool):
    os.environ.setdefault("SDL_AUDIODRIVER", "dummy")  # pygame: no ALSA noise on headless machines
    # optional dependency: the simulator's gymnasium API
    import gym_pusht  # noqa: F401  (registers gym_pusht/PushT-v0)
    import gymnasium as gym

    size = int(task.image_size)
    return gym.make(
        task.env_id,
        obs_type=OBS_MODES[task.obs_mode],
        render_mode="rgb_array",
        observation_width=size,
        observation_height=size,
        max_episode_steps=int(task.max_episode_steps),
        disable_env_checker=True,
    )


class PushTEnv(EnvBase):
    """gym-pusht's ``PushT-v0`` behind the project's env contract (see :mod:`l1flow_rl.envs.registry`).

    Outputs: ``"observation"`` (float32 [D] for state, keypoints and environment_state_agent_pos;
    a TensorDict ``{"rgb": uint8 [3, H, W]}`` for pixels, plus ``"state"`` float32 [2], the agent
    position, for pixels_agent_pos), ``"reward"`` (gym-pusht's ``clip(coverage / 0.95, 0, 1)``),
    ``"coverage"`` (the share of the goal the block covers), ``"success"`` (coverage > 0.95) and the
    done flags. Actions are absolute agent targets in [0, 512]^2.

    ``reset(seed=s)`` seeds the episode; ``reset(options={"reset_to_state": x})`` is passed to
    gym-pusht (see :func:`~l1flow_rl.envs.pusht.geometry.reset_state_for` for an observed state).
    With ``ignore_terminations`` an episode runs to its time limit after success
    (``terminated`` stays False; ``success`` still reports each step).

    Example:
        >>> from l1flow_rl.config import load_task_config
        >>> env = PushTEnv(load_task_config("pusht"))
        >>> env.reset(seed=0)["observation"].shape
        torch.Size([20])
    """

    def __init__(
        self,
        task: TaskConfig,
        *,
        ignore_terminations: bool = False,
        render: bool = True,
        camera: str | None = None,
    ) -> None:
        check_task_simulator(task, "pusht", self)
        if task.obs_mode not in OBS_MODES:
            raise ValueError(
                f"task {task.name!r}: obs_mode must be one of {list(OBS_MODES)}, got {task.obs_mode!r}"
            )
        if camera not in (None, "rgb"):
            raise ValueError(f"PushT has one camera, 'rgb'; got camera={camera!r}")
        super().__init__(device="cpu", batch_size=torch.Size([]))
        self.task, self.ignore_terminations, self.render_enabled = task, ignore_terminations, render
        self._env = _make_gym_env(task, render)
        self._make_specs()

    def _make_specs(self) -> None:
        size = int(self.task.image_size)
        rgb = Bounded(0, 255, shape=(3, size, size), dtype=torch.uint8)
        mode = self.task.obs_mode
        if mode == "pixels":
            observation = Composite(rgb=rgb)
        elif mode == "pixels_agent_pos":
            observation = Composite(state=Unbounded(shape=(2,), dtype=torch.float32), rgb=rgb)
        else:
            observation = Unbounded(shape=(observation_dim(mode),), dtype=torch.float32)
        flag = {"shape": (1,), "dtype": torch.bool}
        self.observation_spec = Composite(
            observation=observation,
            coverage=Unbounded(shape=(1,), dtype=torch.float32),
            success=Categorical(2, **flag),
        )
        self.action_spec = Bounded(0.0, 512.0, shape=(2,), dtype=torch.float32)
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32)
        self.done_spec = Composite(
            done=Categorical(2, **flag), terminated=Categorical(2, **flag), truncated=Categorical(2, **flag)
        )

    # -- conversions -----------------------------------------------------------------------------

    def _observation(self, obs: Any) -> torch.Tensor | TensorDict:
        mode = self.task.obs_mode
        if mode == "state":
            return torch.as_tensor(obs, dtype=torch.float32)
        if mode == "keypoints":  # Diffusion Policy's order: keypoints (x, y) * 9, then agent x, y
            flat = np.concatenate([block_keypoints(obs).reshape(-1), obs[:2]])
            return torch.as_tensor(flat, dtype=torch.float32)
        if mode == "environment_state_agent_pos":
            flat = np.concatenate([obs["environment_state"], obs["agent_pos"]])
            return torch.as_tensor(flat, dtype=torch.float32)
        pixels = obs["pixels"] if mode == "pixels_agent_pos" else obs
        entries = {"rgb": torch.as_tensor(np.ascontiguousarray(pixels)).permute(2, 0, 1).contiguous()}
        if mode == "pixels_agent_pos":
            entries["state"] = torch.as_tensor(obs["agent_pos"], dtype=torch.float32)
        return TensorDict(entries, batch_size=[])

    def _output(self, obs, reward: float, coverage: float, terminated: bool, truncated: bool) -> TensorDict:
        success = coverage > self._env.unwrapped.success_threshold
        terminated = bool(terminated) and not self.ignore_terminations
        flags = torch.tensor([[terminated or truncated], [terminated], [truncated], [success]])
        return TensorDict(
            {
                "observation": self._observation(obs),
                "reward": torch.tensor([reward], dtype=torch.float32),
                "coverage": torch.tensor([coverage], dtype=torch.float32),
                "done": flags[0],
                "terminated": flags[1],
                "truncated": flags[2],
                "success": flags[3],
            },
            batch_size=[],
        )

    # -- EnvBase ---------------------------------------------------------------------------------

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        seed, options = kwargs.pop("seed", None), kwargs.pop("options", None)
        if kwargs:
            raise TypeError(f"PushTEnv.reset: unknown keyword arguments {sorted(kwargs)}")
        if isinstance(seed, (list, tuple, np.ndarray, torch.Tensor)):  # seeded_reset passes [s]
            seeds = np.asarray(seed).reshape(-1).tolist()
            if len(seeds) != 1:
                raise ValueError(f"PushTEnv.reset: one env, got {len(seeds)} seeds")
            seed = seeds[0]
        if seed is None and self._next_seed is not None:  # set_seed(): consecutive seeds from there
            seed, self._next_seed = self._next_seed, self._next_seed + 1
        obs, _ = self._env.reset(seed=None if seed is None else int(seed), options=options)
        coverage = float(self._env.unwrapped._get_coverage())  # reset's info does not report it
        reward = float(np.clip(coverage / self._env.unwrapped.success_threshold, 0.0, 1.0))
        return self._output(obs, reward, coverage, False, False).exclude("reward")

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").detach().cpu().numpy().astype(np.float64)
        obs, reward, terminated, truncated, info = self._env.step(action)
        return self._output(obs, float(reward), float(info["coverage"]), terminated, truncated)

    _next_seed: int | None = None

    def _set_seed(self, seed: int | None) -> None:
        self._next_seed = seed

    # -- extras of the contract ------------------------------------------------------------------

    def render_frames(self) -> torch.Tensor:
        """The visualisation frame (uint8 [H, W, 3], gym-pusht's 680 x 680 render)."""
        if not self.render_enabled:
            raise RuntimeError("this env was made with render=False")
        return torch.as_tensor(np.ascontiguousarray(self._env.render()))

    def sim_state(self) -> np.ndarray:
        """gym-pusht's 5-D state (agent x, y, block x, y, angle in [0, 2 pi)), whatever the obs mode."""
        u = self._env.unwrapped
        return np.array([*u.agent.position, *u.block.position, u.block.angle % (2 * np.pi)])

    def close(self, *, raise_if_closed: bool = True) -> None:
        self._env.close()
        super().close(raise_if_closed=raise_if_closed)

    def __repr__(self) -> str:
        return f"PushTEnv(env_id={self.task.env_id!r}, obs_mode={self.task.obs_mode!r})"
