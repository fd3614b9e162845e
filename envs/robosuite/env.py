"""One robosuite task as an unbatched TorchRL env (the unit a worker process runs).

Hand-written rather than TorchRL's ``RoboHiveEnv``/``GymWrapper``: robosuite is no gymnasium env
(its ``GymWrapper`` flattens every key and hides ``_check_success``), and the observation here is
robomimic's (chosen state keys, upright images named ``<camera>_image``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from l1flow_rl.envs.registry import check_task_simulator
from l1flow_rl.envs.robosuite import sim
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from l1flow_rl.config import TaskConfig

__all__ = ["RobosuiteEnv"]

#: the camera and size of render_frames() (videos), as robomimic's rollouts use
RENDER_CAMERA, RENDER_SIZE = "agentview", 256


class RobosuiteEnv(EnvBase):
    """A robosuite task (``task.env_id``: ``Lift``, ``Stack``, ``PickPlaceCan``, ...) as an
    unbatched TorchRL env; :func:`l1flow_rl.envs.make_env` batches several in worker processes.

    Outputs: ``"observation"`` (state tasks: float32 [D], the ``task.state_keys`` concatenated;
    image tasks: a TensorDict with ``"state"`` and one uint8 [3, H, W] entry per camera named by
    robomimic's key, e.g. ``"agentview_image"``), ``"reward"`` (robosuite's, sparse unless
    ``reward_mode: dense``), ``"done"``/``"terminated"``/``"truncated"`` (truncated at
    ``task.max_episode_steps``; with ``ignore_terminations=False`` success terminates), and
    ``"success"`` from the env's own ``_check_success()``. A simulator exception in ``step`` ends
    the episode with ``"sim_error"``; the next reset rebuilds the env.

    Actions follow the task's controller (``control_mode``, e.g. ``OSC_POSE``) and ``control``:
    ``absolute`` targets [x, y, z, axis-angle, gripper] in the world frame (unbounded spec), or
    ``delta`` in [-1, 1].

    Example:
        >>> from l1flow_rl.config import load_task_config
        >>> env = RobosuiteEnv(load_task_config("robosuite_lift", max_episode_steps=5))
        >>> env.rollout(10).batch_size  # stops at the time limit
        torch.Size([5])
    """

    def __init__(
        self,
        task: TaskConfig,
        *,
        ignore_terminations: bool = True,
        render: bool = True,
        camera: str | None = None,
    ) -> None:
        check_task_simulator(task, "robosuite", self)
        if task.obs_mode not in ("state", "rgb"):
            raise ValueError(f"task {task.name!r}: obs_mode must be 'state' or 'rgb', got {task.obs_mode!r}")
        if not task.state_keys:
            raise ValueError(
                f"task {task.name!r}: state_keys is empty; robosuite tasks name their state keys"
            )
        if task.obs_mode == "rgb" and not task.cameras:
            raise ValueError(f"task {task.name!r}: obs_mode 'rgb' needs cameras (e.g. [agentview])")
        super().__init__(device=torch.device("cpu"), batch_size=torch.Size([]))
        self.task = task
        self.ignore_terminations = ignore_terminations
        self.render_enabled = render
        self.cameras = list(task.cameras) if task.obs_mode == "rgb" else []
        if camera is not None and camera not in self.cameras:
            raise ValueError(f"camera {camera!r} is not one of task {task.name!r}'s cameras {self.cameras}")
        self.env_args = sim.env_args_for_task(task, cameras=self.cameras, render=render)
        self._sim = self._make_sim()
        self._seed: int | None = None
        self._elapsed = 0
        self._broken = False
        self.last_sim_error: str | None = None
        raw = self._sim.reset()
        state, images = sim.observation_arrays(raw, task.state_keys, self.cameras)
        self._last_obs = self._observation(state, images)
        self._make_specs(state.shape, {k: v.shape for k, v in images.items()})

    # -- simulator --------------------------------------------------------------------------------

    def _make_sim(self):
        return sim.make_from_env_args(
            self.env_args, render=self.render_enabled, source=f"task {self.task.name!r}"
        )

    @property
    def sim(self):
        """The robosuite env (``robosuite.environments.*``)."""
        return self._sim

    def _make_specs(self, state_shape: tuple[int, ...], image_shapes: dict[str, tuple[int, ...]]) -> None:
        state = Unbounded(shape=state_shape, dtype=torch.float32)
        if self.task.obs_mode == "state":
            observation = state
        else:
            images = {k: Bounded(0, 255, shape=s, dtype=torch.uint8) for k, s in image_shapes.items()}
            observation = Composite(state=state, **images, shape=())
        flag = {"shape": (1,), "dtype": torch.bool}
        self.observation_spec = Composite(
            observation=observation,
            success=Categorical(2, **flag),
            sim_error=Categorical(2, **flag),
            shape=(),
        )
        low, high = (np.asarray(x, dtype=np.float32) for x in self._sim.action_spec)
        if self.task.control == "absolute":  # arm targets are poses, not [-1, 1] commands
            self.action_spec = Unbounded(shape=low.shape, dtype=torch.float32)
        else:
            self.action_spec = Bounded(
                torch.as_tensor(low), torch.as_tensor(high), shape=low.shape, dtype=torch.float32
            )
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32)
        self.done_spec = Composite(
            done=Categorical(2, **flag),
            terminated=Categorical(2, **flag),
            truncated=Categorical(2, **flag),
            shape=(),
        )

    def _observation(self, state: np.ndarray, images: dict[str, np.ndarray]) -> Tensor | TensorDictBase:
        if self.task.obs_mode == "state":
            return torch.from_numpy(state)
        return TensorDict(
            {"state": torch.from_numpy(state), **{k: torch.from_numpy(v) for k, v in images.items()}}
        )

    def _output(
        self, reward: float, terminated: bool, truncated: bool, success: bool, sim_error: bool
    ) -> TensorDict:
        def flag(value: bool) -> Tensor:
            return torch.tensor([bool(value)])

        return TensorDict(
            {
                "observation": self._last_obs,
                "reward": torch.tensor([float(reward)], dtype=torch.float32),
                "done": flag(terminated or truncated),
                "terminated": flag(terminated),
                "truncated": flag(truncated),
                "success": flag(success),
                "sim_error": flag(sim_error),
            },
            batch_size=[],
        )

    # -- EnvBase ----------------------------------------------------------------------------------

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").detach().cpu().numpy().astype(np.float64)
        self._elapsed += 1
        if not self._broken:
            try:
                raw, reward = sim.step(self._sim, action)
                success = bool(self._sim._check_success())
            except Exception as err:  # a MuJoCo failure ends this episode; the next reset rebuilds
                self._broken, self.last_sim_error = True, f"{type(err).__name__}: {err}"
            else:
                state, images = sim.observation_arrays(raw, self.task.state_keys, self.cameras)
                self._last_obs = self._observation(state, images)
                terminated = success and not self.ignore_terminations
                truncated = self._elapsed >= self.task.max_episode_steps
                return self._output(reward, terminated, truncated, success, False)
        return self._output(0.0, False, True, False, True)

    def _reset(
        self, tensordict: TensorDictBase | None = None, *, seed: Any = None, **kwargs
    ) -> TensorDictBase:
        if kwargs:
            raise TypeError(f"RobosuiteEnv.reset got unexpected keyword arguments {sorted(kwargs)}")
        if self._broken:
            self._sim.close()
            self._sim = self._make_sim()
            self._broken, self.last_sim_error = False, None
        if seed is None and self._seed is not None:  # set_seed(): consecutive episode seeds
            seed, self._seed = self._seed, self._seed + 1
        if seed is not None:
            seed = int(np.asarray(seed).reshape(-1)[0])
        sim.seed_episode(self._sim, seed)
        raw = self._sim.reset()
        self._elapsed = 0
        state, images = sim.observation_arrays(raw, self.task.state_keys, self.cameras)
        self._last_obs = self._observation(state, images)
        return self._output(0.0, False, False, bool(self._sim._check_success()), False).exclude("reward")

    def _set_seed(self, seed: int | None) -> None:
        self._seed = seed

    # -- extras -----------------------------------------------------------------------------------

    def sim_error_message(self) -> str | None:
        """The simulator exception that ended the current episode, until the next reset."""
        return self.last_sim_error

    def render_frames(self) -> Tensor:
        """The agentview camera's frame, uint8 [256, 256, 3] upright (needs ``render=True``)."""
        if not self.render_enabled:
            raise RuntimeError("make the env with render=True to render frames")
        frame = self._sim.sim.render(camera_name=RENDER_CAMERA, width=RENDER_SIZE, height=RENDER_SIZE)
        return torch.from_numpy(np.ascontiguousarray(frame[::-1]))

    def close(self, *, raise_if_closed: bool = True) -> None:
        if getattr(self, "_sim", None) is not None:
            self._sim.close()
            self._sim = None
        super().close(raise_if_closed=raise_if_closed)

    def __repr__(self) -> str:
        task = self.task
        return f"RobosuiteEnv(env_id={task.env_id!r}, obs_mode={task.obs_mode!r}, control={task.control!r})"
