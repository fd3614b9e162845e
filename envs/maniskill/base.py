"""What every ManiSkill TorchRL env of this package shares, whatever runs the simulator: argument
checks, specs, the output tensordict, and per-episode seeds."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from l1flow_rl.envs.registry import check_task_simulator
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from l1flow_rl.config import TaskConfig

__all__ = ["ManiSkillEnvBase"]


class ManiSkillEnvBase(EnvBase):
    """Base of :class:`~l1flow_rl.envs.maniskill.env.ManiSkillEnv` (the simulator in this process)
    and :class:`~l1flow_rl.envs.maniskill.async_env.ManiSkillAsyncEnv` (one simulator per worker
    process). Subclasses hold ``_sim_envs`` envs whose values arrive with a leading dim of that size,
    and call :meth:`_make_specs` once they know the observation and action shapes."""

    def __init__(
        self,
        task: TaskConfig,
        *,
        batch_size: torch.Size,
        device: torch.device,
        ignore_terminations: bool,
        render: bool,
        camera: str | None,
        reconfigure_each_episode: bool,
    ) -> None:
        check_task_simulator(task, "maniskill", self)
        if task.obs_mode not in ("state", "rgb"):
            raise ValueError(f"task {task.name!r}: obs_mode must be 'state' or 'rgb', got {task.obs_mode!r}")
        if reconfigure_each_episode and device.type != "cpu":
            raise ValueError(
                "reconfigure_each_episode needs physx_cpu: physx_cuda cannot rebuild some envs of a scene"
            )
        super().__init__(device=device, batch_size=batch_size)
        self.task = task
        self.ignore_terminations = ignore_terminations
        self.render_enabled = render
        self.camera = camera
        self.reconfigure_each_episode = reconfigure_each_episode
        self._sim_envs = int(np.prod(batch_size)) if len(batch_size) else 1
        self._seed: int | None = None

    @property
    def sim_kwargs(self) -> dict[str, Any]:
        """The keyword arguments, past the task, that make an env of this one's settings."""
        return {
            "ignore_terminations": self.ignore_terminations,
            "render": self.render_enabled,
            "camera": self.camera,
            "reconfigure_each_episode": self.reconfigure_each_episode,
        }

    # -- specs -----------------------------------------------------------------------------------

    def _make_specs(
        self, obs_shapes: dict[str, tuple[int, ...]], action_low: np.ndarray, action_high: np.ndarray
    ) -> None:
        """``obs_shapes``: one env's ``{"state": (D,)}`` (state) or ``{"state": (D,), "rgb": (3, H, W)}``."""
        batch, device = self.batch_size, self.device
        if self.task.obs_mode == "state":
            observation = Unbounded(shape=(*batch, *obs_shapes["state"]), dtype=torch.float32, device=device)
        else:
            observation = Composite(
                state=Unbounded(shape=(*batch, *obs_shapes["state"]), dtype=torch.float32, device=device),
                rgb=Bounded(0, 255, shape=(*batch, *obs_shapes["rgb"]), dtype=torch.uint8, device=device),
                shape=batch,
                device=device,
            )
        flag = {"shape": (*batch, 1), "dtype": torch.bool, "device": device}
        self.observation_spec = Composite(
            observation=observation,
            success=Categorical(2, **flag),
            sim_error=Categorical(2, **flag),
            shape=batch,
            device=device,
        )
        low = torch.as_tensor(np.asarray(action_low, dtype=np.float32), device=device)
        high = torch.as_tensor(np.asarray(action_high, dtype=np.float32), device=device)
        self.action_spec = Bounded(
            low=low.expand(*batch, *low.shape),
            high=high.expand(*batch, *high.shape),
            shape=(*batch, *low.shape),
            dtype=torch.float32,
            device=device,
        )
        self.reward_spec = Unbounded(shape=(*batch, 1), dtype=torch.float32, device=device)
        self.done_spec = Composite(
            done=Categorical(2, **flag),
            terminated=Categorical(2, **flag),
            truncated=Categorical(2, **flag),
            shape=batch,
            device=device,
        )

    # -- conversions -----------------------------------------------------------------------------

    def _unsim(self, value: Any) -> Tensor:
        """A tensor or array with a leading dim of ``_sim_envs`` -> [*batch, ...] on this env's device."""
        value = torch.as_tensor(value).to(self.device)
        return value.squeeze(0) if not self.batch_size else value

    def _bools(self, value: Any) -> Tensor:
        return torch.as_tensor(value, device=self.device).to(torch.bool).reshape(-1).expand(self._sim_envs)

    def _output(
        self,
        obs: Tensor | TensorDictBase,
        reward: Any,
        terminated: Any,
        truncated: Any,
        success: Any,
        sim_error: Any,
    ) -> TensorDictBase:
        """The step tensordict; every value but ``obs`` has ``_sim_envs`` entries (``success=None``:
        the task has no success criterion, ``sim_error`` may be one bool for all envs)."""
        terminated, truncated = self._bools(terminated), self._bools(truncated)
        success = self._bools(False if success is None else success)
        # one stack, then contiguous [*batch, 1] rows of it: this runs at every step, and each
        # conversion costs time there
        flags = torch.stack([terminated | truncated, terminated, truncated, success, self._bools(sim_error)])
        flags = flags.reshape(5, *self.batch_size, 1)
        reward = torch.as_tensor(reward, dtype=torch.float32).reshape(self._sim_envs, 1)
        names = ("done", "terminated", "truncated", "success", "sim_error")
        return TensorDict(
            {
                "observation": obs,
                "reward": self._unsim(reward),
                **dict(zip(names, flags)),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    # -- seeds -----------------------------------------------------------------------------------

    def _episode_seeds(self, seed: Any, count: int) -> list[int] | None:
        """The seeds of the ``count`` envs being reset: those given, else consecutive ones from
        ``set_seed``, else None (the simulator draws them)."""
        if seed is None and self._seed is not None:  # set_seed(): consecutive seeds from there on
            seed = list(range(self._seed, self._seed + count))
            self._seed += count
        if seed is None:
            return None
        seeds = [
            int(s) for s in (seed.reshape(-1).tolist() if isinstance(seed, Tensor) else np.atleast_1d(seed))
        ]
        if len(seeds) != count:
            raise ValueError(f"reset(seed=...): got {len(seeds)} seeds for {count} envs being reset")
        return seeds

    def _set_seed(self, seed: int | None) -> None:
        self._seed = seed

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(env_id={self.task.env_id!r}, obs_mode={self.task.obs_mode!r}, "
            f"batch_size={tuple(self.batch_size)}, device={self.device})"
        )
