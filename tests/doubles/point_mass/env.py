"""A 2-D point mass that must reach a goal: a complete simulator in pure torch, batched in one process.

State per env: position p and velocity v in [-1, 1]^2, and the goal g. An action a in [-1, 1]^2
accelerates the mass: v <- (1 - damping) v + GAIN a, p <- clip(p + v, -1, 1). The observation is
[p, v, g] (6 floats); success is |p - g| < goal_tolerance. Each episode's start and goal come from
its seed alone, so a seed starts the same episode in any env slot, in any order.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from l1flow_rl.config import TaskConfig

__all__ = ["CONTROL_MODES", "ENV_IDS", "GAIN", "OBS_DIM", "PointMassEnv", "episode_start", "expert_action"]

ENV_IDS = ("PointMassReach-v0",)
CONTROL_MODES = ("acceleration",)
REWARD_MODES = ("dense", "normalized_dense", "sparse")
GAIN = 0.05
OBS_DIM, ACTION_DIM = 6, 2
FRAME = 32  # render_frames() size


def episode_start(seed: int) -> tuple[Tensor, Tensor]:
    """The start position and goal of the episode of ``seed``, at least 0.3 apart."""
    generator = torch.Generator().manual_seed(int(seed))
    while True:
        start, goal = (torch.rand(2, 2, generator=generator) * 1.6 - 0.8).unbind(0)
        if (goal - start).norm() > 0.3:
            return start, goal


class PointMassEnv(EnvBase):
    """``num_envs`` point masses, batch size ``[num_envs]``, honouring the env contract of
    :mod:`l1flow_rl.envs.registry` (observation, reward, done flags, success, seeded partial
    resets, ``render_frames()``) plus a per-step ``"distance"`` to the goal."""

    def __init__(
        self,
        task: TaskConfig,
        num_envs: int,
        device: torch.device | str = "cpu",
        *,
        ignore_terminations: bool = True,
        render: bool = True,
        camera: str | None = None,
        goal_tolerance: float = 0.05,
    ) -> None:
        if task.env_id not in ENV_IDS:
            raise ValueError(f"task {task.name!r}: point_mass has env ids {ENV_IDS}, got {task.env_id!r}")
        if task.control_mode not in CONTROL_MODES:
            raise ValueError(
                f"task {task.name!r}: point_mass has control modes {CONTROL_MODES}, got {task.control_mode!r}"
            )
        if task.reward_mode not in REWARD_MODES:
            raise ValueError(
                f"task {task.name!r}: point_mass has reward modes {REWARD_MODES}, got {task.reward_mode!r}"
            )
        if camera is not None:
            raise ValueError(f"point_mass has no cameras, got camera={camera!r}")
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.task, self.num_envs = task, num_envs
        self.ignore_terminations, self.render_enabled = ignore_terminations, render
        self.goal_tolerance = float(goal_tolerance)
        self.damping = float(task.env.get("damping", 0.2))
        self._seed: int | None = None
        self._pos = torch.zeros(num_envs, 2, device=self.device)
        self._vel = torch.zeros_like(self._pos)
        self._goal = torch.zeros_like(self._pos)
        self._t = torch.zeros(num_envs, dtype=torch.long, device=self.device)
        batch, flag = (num_envs,), {"shape": (num_envs, 1), "dtype": torch.bool, "device": self.device}
        self.observation_spec = Composite(
            observation=Unbounded((*batch, OBS_DIM), device=self.device),
            success=Categorical(2, **flag),
            distance=Unbounded((*batch, 1), device=self.device),
            shape=batch,
        )
        self.action_spec = Bounded(-1.0, 1.0, (*batch, ACTION_DIM), device=self.device)
        self.reward_spec = Unbounded((*batch, 1), device=self.device)
        self.done_spec = Composite(
            done=Categorical(2, **flag),
            terminated=Categorical(2, **flag),
            truncated=Categorical(2, **flag),
            shape=batch,
        )

    # -- outputs ---------------------------------------------------------------------------------

    def _distance(self) -> Tensor:
        return (self._goal - self._pos).norm(dim=-1, keepdim=True)

    def _reward(self, distance: Tensor, success: Tensor) -> Tensor:
        if self.task.reward_mode == "sparse":
            return success.float()
        if self.task.reward_mode == "dense":
            return -distance
        return 1 - torch.tanh(5 * distance)

    def _output(self, terminated: Tensor, truncated: Tensor) -> TensorDict:
        distance = self._distance()
        success = distance < self.goal_tolerance
        return TensorDict(
            {
                "observation": torch.cat([self._pos, self._vel, self._goal], -1),
                "reward": self._reward(distance, success),
                "success": success,
                "distance": distance,
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    # -- EnvBase ---------------------------------------------------------------------------------

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").to(self.device).clamp(-1, 1)
        self._vel = (1 - self.damping) * self._vel + GAIN * action
        self._pos = (self._pos + self._vel).clamp(-1, 1)
        self._t += 1
        success = self._distance() < self.goal_tolerance
        terminated = success & (not self.ignore_terminations)
        truncated = (self._t >= self.task.max_episode_steps).unsqueeze(-1)
        return self._output(terminated, truncated & ~terminated)

    def _reset(self, tensordict: TensorDictBase | None = None, *, seed=None, **kwargs) -> TensorDictBase:
        if kwargs:
            raise TypeError(f"PointMassEnv.reset got unexpected keyword arguments {sorted(kwargs)}")
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is None:
            idx = list(range(self.num_envs))
        else:
            idx = mask.reshape(self.num_envs).nonzero().squeeze(-1).tolist()
        for i, s in zip(idx, self._episode_seeds(seed, len(idx))):
            start, goal = episode_start(s)
            self._pos[i], self._goal[i] = start.to(self.device), goal.to(self.device)
            self._vel[i] = 0.0
            self._t[i] = 0
        no = torch.zeros(self.num_envs, 1, dtype=torch.bool, device=self.device)
        return self._output(no, no).exclude("reward")

    def _episode_seeds(self, seed, count: int) -> list[int]:
        """One seed per env being reset: those given, else consecutive ones from ``set_seed``, else
        drawn from torch's global generator."""
        if seed is None and self._seed is not None:
            seed = list(range(self._seed, self._seed + count))
            self._seed += count
        if seed is None:
            return torch.randint(0, 2**31 - 1, (count,)).tolist()
        seeds = [int(s) for s in (seed.reshape(-1).tolist() if isinstance(seed, Tensor) else list(seed))]
        if len(seeds) != count:
            raise ValueError(f"reset(seed=...): got {len(seeds)} seeds for {count} envs being reset")
        return seeds

    def _set_seed(self, seed: int | None) -> None:
        self._seed = seed

    # -- extras of the contract ------------------------------------------------------------------

    def render_frames(self) -> Tensor:
        """uint8 [N, 32, 32, 3]: white background, the goal green, the mass red."""
        if not self.render_enabled:
            raise RuntimeError("make the env with render=True to render frames")
        frames = torch.full((self.num_envs, FRAME, FRAME, 3), 255, dtype=torch.uint8)

        def pixel(xy: Tensor) -> Sequence[int]:
            return ((xy.cpu() + 1) / 2 * (FRAME - 1)).round().long().tolist()

        for i in range(self.num_envs):
            gx, gy = pixel(self._goal[i])
            px, py = pixel(self._pos[i])
            frames[i, gy, gx] = torch.tensor([0, 200, 0], dtype=torch.uint8)
            frames[i, py, px] = torch.tensor([220, 0, 0], dtype=torch.uint8)
        return frames

    def sim_error_message(self) -> str | None:
        return None  # this simulator never fails


def expert_action(observation: Tensor) -> Tensor:
    """The scripted controller (a clipped PD law towards the goal) on observations [..., 6]."""
    pos, vel, goal = observation[..., 0:2], observation[..., 2:4], observation[..., 4:6]
    return (3.0 * (goal - pos) - 6.0 * vel).clamp(-1, 1)
