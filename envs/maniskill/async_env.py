"""Several physx_cpu ManiSkill envs, one per worker process, as one batched TorchRL env.

The workers run gymnasium's ``AsyncVectorEnv`` (autoreset off: its ``SAME_STEP`` mode breaks on
ManiSkill's reset info, and resets here are per env and seeded), each around an unbatched
:class:`~l1flow_rl.envs.maniskill.env.ManiSkillEnv`, so that observations, seeds and simulator
error handling are those of the in-process adapter. TorchRL's ``ParallelEnv`` does the same job
(``make_env(..., cpu_backend="parallel")``) but costs this process more CPU per batched step
than a physx_cpu step takes; ``AsyncVectorEnv`` moves flat numpy observations through shared
memory for a fraction of that (both against the raw simulator:
``benchmarks/results/env_throughput_state.json``).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
import torch
from l1flow_rl.envs.maniskill.base import ManiSkillEnvBase
from l1flow_rl.envs.maniskill.env import INSTALL_HINT, ManiSkillEnv
from l1flow_rl.envs.workers import (
    check_main_guard,
    explain_worker_start_failure,
    simulator_forkserver,
)
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from l1flow_rl.config import TaskConfig

try:
    import gymnasium as gym
    from gymnasium.vector.async_vector_env import _async_worker
except ImportError as err:  # gymnasium comes with ManiSkill
    raise ImportError(INSTALL_HINT) from err

__all__ = ["ManiSkillAsyncEnv", "use_forkserver"]

#: what the forkserver imports once, so that each worker forks with the simulator already imported
_WORKER_PRELOAD = [
    "torch",
    "torchrl.envs",
    "gymnasium.vector",
    "mani_skill.envs",
    "l1flow_rl.envs.maniskill.env",
    "l1flow_rl.envs.maniskill.async_env",
]


def use_forkserver() -> str:
    """The start method for simulator workers: forked from a clean server that has the simulator
    imported (a spawned worker re-imports everything, ~10 s each here; a plain fork of a process
    with ManiSkill in it hung). Scripts that make workers need the ``__main__`` guard."""
    return simulator_forkserver(_WORKER_PRELOAD)


class _WorkerGymEnv(gym.Env):
    """An unbatched ManiSkillEnv behind gymnasium's API, the unit an ``AsyncVectorEnv`` worker runs.

    Observations are the adapter's flat ones (state [D], or ``{"state": [D], "rgb": [3, H, W]}``),
    and ``info`` holds only what the batched env reads: ``success`` and ``sim_error``.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"]}

    def __init__(self, env: ManiSkillEnv) -> None:
        if env.batch_size:
            raise ValueError(f"a worker runs an unbatched env, got batch size {tuple(env.batch_size)}")
        self.env = env
        spec = env.observation_spec["observation"]
        if env.task.obs_mode == "state":
            self.observation_space = gym.spaces.Box(-np.inf, np.inf, tuple(spec.shape), np.float32)
        else:
            self.observation_space = gym.spaces.Dict(
                state=gym.spaces.Box(-np.inf, np.inf, tuple(spec["state"].shape), np.float32),
                rgb=gym.spaces.Box(0, 255, tuple(spec["rgb"].shape), np.uint8),
            )
        action = env.action_spec.space
        self.action_space = gym.spaces.Box(action.low.numpy(), action.high.numpy(), dtype=np.float32)
        self.render_mode = "rgb_array" if env.render_enabled else None

    @staticmethod
    def _numpy(obs: Tensor | TensorDictBase) -> Any:
        return obs.numpy() if isinstance(obs, Tensor) else {k: v.numpy() for k, v in obs.items()}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if options:
            raise ValueError(f"reset options are not supported by the worker env, got {sorted(options)}")
        td = self.env._reset(None, seed=None if seed is None else [seed])  # its own reset: no checks needed
        info = {"success": bool(td.get("success")), "sim_error": False}
        return self._numpy(td.get("observation")), info

    def step(self, action: np.ndarray):
        obs, reward, terminated, truncated, success, sim_error = self.env.sim_step(
            torch.as_tensor(np.asarray(action, dtype=np.float32)).unsqueeze(0)
        )
        info = {"success": success is not None and bool(success), "sim_error": sim_error}
        return self._numpy(obs), float(reward), bool(terminated), bool(truncated), info

    def render_frames(self) -> np.ndarray:
        return self.env.render_frames().numpy()

    def sim_error_message(self) -> str | None:
        return self.env.sim_error_message()

    def close(self) -> None:
        self.env.close(raise_if_closed=False)


def _worker(*args: Any) -> None:
    """gymnasium's ``AsyncVectorEnv`` worker loop, which exits quietly once the main process has dropped
    the vector env without closing it, or died.

    Dropping an unclosed env (a script whose ``main()`` returns or calls ``sys.exit`` without
    ``env.close()``) runs gymnasium's ``__del__``, which sends the workers SIGTERM and closes their
    pipes. Simulator workers ignore SIGTERM (:func:`~l1flow_rl.envs.workers.signal_safe_factory`
    says why), so they end on the closed pipe instead: gymnasium's loop reports that ``EOFError``
    back down the same closed pipe, and each worker printed a ``BrokenPipeError`` traceback. A
    report that fails on a broken pipe has nobody to go to; any other error still propagates.
    """
    try:
        _async_worker(*args)
    except (BrokenPipeError, ConnectionResetError) as err:
        if not isinstance(err.__context__, (EOFError, ConnectionError)):
            raise


class _WorkerFactory:
    """Makes a worker's env. AsyncVectorEnv also calls it once in this process (to read the spaces):
    only in a worker does it drop torch to one thread, as ParallelEnv's workers do, since the
    workers already use every core."""

    def __init__(self, make_env: Callable[[], ManiSkillEnv]) -> None:
        self.make_env = make_env
        self.parent_pid = os.getpid()

    def __call__(self) -> _WorkerGymEnv:
        if os.getpid() != self.parent_pid:
            torch.set_num_threads(1)
        return _WorkerGymEnv(self.make_env())


class ManiSkillAsyncEnv(ManiSkillEnvBase):
    """``num_envs`` physx_cpu ManiSkill envs, one per worker process, as one TorchRL env of batch
    size ``[num_envs]`` on the CPU.

    Same outputs as :class:`~l1flow_rl.envs.maniskill.env.ManiSkillEnv` (``"observation"``,
    ``"reward"``, done flags, ``"success"``, ``"sim_error"``), same ``reset(seed=...)`` (one seed
    per env being reset; a ``"_reset"`` mask resets only those envs, the others go on), and the
    same simulator-error handling, each worker on its own: a worker whose simulator raised ends
    its episode with ``sim_error=True`` and rebuilds at its next reset. ``worker_env`` makes each
    worker's unbatched env (a ``ManiSkillEnv`` subclass, e.g. to inject failures in tests).

    Workers start through multiprocessing's forkserver: a script that makes one needs the
    ``if __name__ == "__main__":`` guard.

    Example:
        >>> from l1flow_rl.config import load_task_config
        >>> env = ManiSkillAsyncEnv(load_task_config("maniskill_pushcube", max_episode_steps=5), 2)
        >>> env.rollout(10).batch_size  # stops at the time limit
        torch.Size([2, 5])
        >>> env.close()
    """

    def __init__(
        self,
        task: TaskConfig,
        num_envs: int,
        *,
        ignore_terminations: bool = True,
        render: bool = True,
        camera: str | None = None,
        reconfigure_each_episode: bool = False,
        worker_env: Callable[..., ManiSkillEnv] = ManiSkillEnv,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        super().__init__(
            task,
            batch_size=torch.Size([num_envs]),
            device=torch.device("cpu"),
            ignore_terminations=ignore_terminations,
            render=render,
            camera=camera,
            reconfigure_each_episode=reconfigure_each_episode,
        )
        # optional dependency: the simulator's gymnasium API
        from gymnasium.vector import AsyncVectorEnv, AutoresetMode

        what = f"ManiSkill on the CPU with num_envs={num_envs} ({task.name!r})"
        check_main_guard(what)
        make = _WorkerFactory(functools.partial(worker_env, task, num_envs=None, **self.sim_kwargs))
        with explain_worker_start_failure(what):
            self._vec = AsyncVectorEnv(
                [make] * num_envs,
                context=use_forkserver(),
                autoreset_mode=AutoresetMode.DISABLED,
                copy=False,  # _observation copies out of the shared buffers itself
                worker=_worker,
            )
        space = self._vec.single_observation_space
        if task.obs_mode == "state":
            obs_shapes = {"state": tuple(space.shape)}
        else:
            obs_shapes = {key: tuple(space[key].shape) for key in ("state", "rgb")}
        action_space = self._vec.single_action_space
        self._make_specs(obs_shapes, action_space.low, action_space.high)
        self._last_obs: Tensor | TensorDictBase | None = None

    def _observation(self, obs: Any) -> Tensor | TensorDictBase:
        # torch.tensor copies: the shared-memory buffers are overwritten by the next step
        if self.task.obs_mode == "state":
            return torch.tensor(obs)
        return TensorDict(
            {key: torch.tensor(obs[key]) for key in ("state", "rgb")}, batch_size=self.batch_size
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").detach().cpu().numpy()
        obs, reward, terminated, truncated, info = self._vec.step(action)
        self._last_obs = self._observation(obs)
        return self._output(self._last_obs, reward, terminated, truncated, info["success"], info["sim_error"])

    def _reset(
        self, tensordict: TensorDictBase | None = None, *, seed: Any = None, **kwargs
    ) -> TensorDictBase:
        if kwargs:
            raise TypeError(f"ManiSkillAsyncEnv.reset got unexpected keyword arguments {sorted(kwargs)}")
        n = self._sim_envs
        mask = None if tensordict is None else tensordict.get("_reset", None)
        reset = np.ones(n, dtype=bool) if mask is None else mask.reshape(n).cpu().numpy().astype(bool)
        idx = np.flatnonzero(reset)
        seeds = self._episode_seeds(seed, len(idx))
        if self._last_obs is None and len(idx) < n:
            raise RuntimeError("the first reset of ManiSkillAsyncEnv must reset every env")
        success = np.zeros(n, dtype=bool)  # rows not reset are not read (TorchRL keeps their data)
        if len(idx) > 0:
            per_env: list[int | None] = [None] * n  # AsyncVectorEnv takes one seed per env
            for i, s in zip(idx.tolist(), seeds or []):
                per_env[i] = s
            obs, info = self._vec.reset(seed=per_env, options={"reset_mask": reset})
            self._last_obs = self._observation(obs)
            success = info.get("success", success)
        no = np.zeros(n, dtype=bool)
        return self._output(self._last_obs, np.zeros(n), no, no, success, False).exclude("reward")

    def sim_error_message(self) -> list[str | None]:
        """Per env: the simulator exception that ended its current episode, until its next reset."""
        return list(self._vec.call("sim_error_message"))

    def render_frames(self) -> Tensor:
        """The render camera's RGB frame per env: uint8 [num_envs, H, W, 3]."""
        if not self.render_enabled:
            raise RuntimeError("make the env with render=True to render frames")
        return torch.from_numpy(np.stack(self._vec.call("render_frames")))

    def close(self, *, raise_if_closed: bool = True) -> None:
        if getattr(self, "_vec", None) is not None:
            self._vec.close()
            self._vec = None
        super().close(raise_if_closed=raise_if_closed)
