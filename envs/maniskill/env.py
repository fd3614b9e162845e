"""A ManiSkill task as a TorchRL ``EnvBase``: physx_cpu (one env per process) or physx_cuda (N in one).

Hand-written rather than ``GymWrapper`` because none of TorchRL's wrappers handles what ManiSkill
needs: batched observations with an unbatched action space, partial resets by ``env_idx`` on the
GPU, per-episode seeds, and surviving a simulator exception without killing a worker process.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from l1flow_rl.envs.maniskill.base import ManiSkillEnvBase
from l1flow_rl.envs.maniskill.obs import flatten_maniskill_obs
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from l1flow_rl.config import TaskConfig

INSTALL_HINT = "pip install 'l1flow-rl[maniskill]' (and a Vulkan driver: ./install.sh maniskill)"

__all__ = ["ManiSkillEnv", "make_gym_env"]


def _import_maniskill():
    try:
        # optional dependency: the simulator's gymnasium API
        import gymnasium as gym
        import mani_skill.envs  # noqa: F401  (registers the tasks with gymnasium)
    except ImportError as err:
        raise ImportError(INSTALL_HINT) from err
    return gym


def make_gym_env(task: TaskConfig, num_envs: int, device: torch.device, *, render: bool = True):
    """The raw ManiSkill gymnasium env that :class:`ManiSkillEnv` wraps (physx_cpu on the CPU,
    physx_cuda on ``device``), configured from the task; also the baseline in the benchmarks."""
    gym = _import_maniskill()
    kwargs: dict[str, Any] = dict(task.env)
    if task.obs_mode == "rgb":
        kwargs.setdefault("sensor_configs", {"width": task.image_size, "height": task.image_size})
    if not torch.cuda.is_available():
        # No GPU renderer to find: say so, instead of ManiSkill warning on every env it makes.
        kwargs.setdefault("render_backend", "cpu")
    if device.type == "cpu":
        backend = "physx_cpu"
    else:
        backend = "physx_cuda" if device.index is None else f"physx_cuda:{device.index}"
    if backend.startswith("physx_cuda"):
        _check_physx_gpu_library()
    try:
        return gym.make(
            task.env_id,
            num_envs=num_envs,
            obs_mode=task.obs_mode,
            control_mode=task.control_mode,
            reward_mode=task.reward_mode,
            max_episode_steps=task.max_episode_steps,
            sim_backend=backend,
            render_mode="rgb_array" if render else None,
            **kwargs,
        )
    except RuntimeError as err:
        if any(marker in str(err).lower() for marker in ("physical device", "vulkan", "vk::")):
            raise RuntimeError(f"{err}\n{VULKAN_HINT}") from err
        raise


def physx_gpu_library() -> tuple[Path, str]:
    """Where SAPIEN looks for PhysX's GPU library (``libPhysXGpu_64.so``, not in its wheel) and the
    release archive it downloads it from on first use of physx_cuda."""
    # optional dependency: the simulator (maniskill extra)
    import sapien

    version = sapien.physx.version()
    url = f"https://github.com/sapien-sim/physx-precompiled/releases/download/{version}/linux-so.zip"
    return Path.home() / ".sapien" / "physx" / version / "libPhysXGpu_64.so", url


def _check_physx_gpu_library() -> None:
    """Fetch PhysX's GPU library the way SAPIEN does, but fail with the file and URL named: offline,
    SAPIEN's own download ends in a bare connection error deep inside ``gym.make``."""
    path, url = physx_gpu_library()
    if path.is_file():
        return
    # optional dependency: the simulator (maniskill extra)
    import sapien

    try:
        sapien.physx.enable_gpu()  # downloads the library, then loads it
    except Exception as err:
        raise RuntimeError(
            f"physx_cuda needs PhysX's GPU library {path}, which SAPIEN downloads from {url} on first use, "
            f"and that failed ({type(err).__name__}: {err}). On a machine without access to GitHub, "
            f"download the zip elsewhere and unzip it into {path.parent}."
        ) from err


VULKAN_HINT = (
    "SAPIEN (ManiSkill) found no usable Vulkan device. Without a GPU driver it needs Mesa lavapipe >= 24.3 "
    "and libvulkan1; on Debian bookworm: add bookworm-backports and run "
    "'apt-get install -t bookworm-backports mesa-vulkan-drivers && apt-get install libvulkan1' "
    "(./install.sh does this)."
)


class ManiSkillEnv(ManiSkillEnvBase):
    """One ManiSkill task, one TorchRL env.

    ``num_envs=None`` gives an unbatched env (batch size ``[]``), the unit a CPU worker process
    runs; ``num_envs=N`` gives batch size ``[N]``. On ``device="cpu"`` ManiSkill runs physx_cpu,
    which holds one env per process (N must be 1: use :func:`~l1flow_rl.envs.make_env`, which
    spreads CPU envs over worker processes); on a CUDA device it runs physx_cuda with N envs in
    one process and every tensor stays on that device.

    Outputs: ``"observation"`` (state: float [*B, D]; rgb: TensorDict ``{"state", "rgb" uint8
    [*B, 3, H, W]}``), ``"reward"``, ``"done"``/``"terminated"``/``"truncated"`` (truncated at the
    task's ``max_episode_steps``), ``"success"`` (ManiSkill's ``info["success"]``) and
    ``"sim_error"``. With ``ignore_terminations=True`` (ManiSkill's evaluation setting) success
    never ends an episode. A simulator exception in ``step`` ends the episode(s) it hit with
    ``sim_error=True`` (message from :meth:`sim_error_message`) instead of raising; the next reset
    rebuilds the simulator. ``reset(seed=...)`` takes one seed per env being reset.

    PhysX keeps solver state across ManiSkill resets, so an episode's trajectory depends slightly
    on the episodes run before it in the same scene (raw ManiSkill does the same; contact-rich
    episodes can diverge). ``reconfigure_each_episode=True`` (CPU only) rebuilds the scene at every
    reset, so that an episode depends on its seed alone, at the cost of a scene build per reset.

    Example:
        >>> from l1flow_rl.config import load_task_config
        >>> env = ManiSkillEnv(load_task_config("maniskill_pushcube", max_episode_steps=5))
        >>> env.rollout(10).batch_size  # stops at the time limit
        torch.Size([1, 5])
    """

    def __init__(
        self,
        task: TaskConfig,
        *,
        num_envs: int | None = 1,
        device: str | torch.device = "cpu",
        ignore_terminations: bool = True,
        render: bool = True,
        camera: str | None = None,
        reconfigure_each_episode: bool = False,
    ) -> None:
        device = torch.device(device)
        if num_envs is not None and num_envs < 1:
            raise ValueError(f"num_envs must be >= 1 or None, got {num_envs}")
        if device.type == "cpu" and num_envs not in (None, 1):
            raise ValueError(
                f"ManiSkill's physx_cpu backend runs one env per process, got num_envs={num_envs}; "
                "use l1flow_rl.envs.make_env (worker processes) or a CUDA device"
            )
        super().__init__(
            task,
            batch_size=torch.Size([] if num_envs is None else [num_envs]),
            device=device,
            ignore_terminations=ignore_terminations,
            render=render,
            camera=camera,
            reconfigure_each_episode=reconfigure_each_episode,
        )
        self.last_sim_error: str | None = None
        self._broken = False
        self._gym_env = self._make_sim()
        space = self.sim.single_observation_space
        if task.obs_mode == "state":
            obs_shapes = {"state": tuple(space.shape)}
        else:
            obs_shapes = {
                k: tuple(v.shape) for k, v in flatten_maniskill_obs(space.sample(), camera=camera).items()
            }
        action_space = self.sim.single_action_space
        self._make_specs(obs_shapes, action_space.low, action_space.high)
        self._last_obs: TensorDictBase | Tensor | None = None
        self._last_success: Tensor | None = None

    # -- simulator --------------------------------------------------------------------------------

    def _make_sim(self):
        return make_gym_env(self.task, self._sim_envs, self.device, render=self.render_enabled)

    @property
    def sim(self):
        """The underlying ManiSkill ``BaseEnv`` (``gym_env.unwrapped``)."""
        return self._gym_env.unwrapped

    # -- conversions -----------------------------------------------------------------------------

    def _observation(self, raw: Any) -> Tensor | TensorDictBase:
        if self.task.obs_mode == "state":
            return self._unsim(raw).to(torch.float32)
        flat = flatten_maniskill_obs(raw, camera=self.camera)
        return TensorDict(
            {k: self._unsim(v) for k, v in flat.items()}, batch_size=self.batch_size, device=self.device
        )

    # -- EnvBase ---------------------------------------------------------------------------------

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        return self._output(*self.sim_step(action if self.batch_size else action.unsqueeze(0)))

    def sim_step(self, action: Tensor) -> tuple[Any, Any, Any, Any, Any, bool]:
        """One simulator step on a ``[num_envs or 1, A]`` action, without building a tensordict (a
        worker process's path): observation (this env's layout), then reward, terminated,
        truncated, success (or None) with a leading dim of ManiSkill's env count, and sim_error."""
        n = self._sim_envs
        if not self._broken:
            try:
                obs, reward, terminated, truncated, info = self._gym_env.step(action)
            except Exception as err:  # a simulator failure ends these episodes; the next reset rebuilds
                self._broken = True
                self.last_sim_error = f"{type(err).__name__}: {err}"
            else:
                if self.ignore_terminations:
                    terminated = torch.zeros_like(torch.as_tensor(terminated))
                self._last_obs = self._observation(obs)
                success = info.get("success") if isinstance(info, dict) else None
                return self._last_obs, reward, terminated, truncated, success, False
        failed = torch.ones(n, dtype=torch.bool, device=self.device)
        return self._last_obs, torch.zeros(n), ~failed, failed, None, True

    def _reset(
        self, tensordict: TensorDictBase | None = None, *, seed: Any = None, **kwargs
    ) -> TensorDictBase:
        if kwargs:
            raise TypeError(f"ManiSkillEnv.reset got unexpected keyword arguments {sorted(kwargs)}")
        mask = None if tensordict is None else tensordict.get("_reset", None)
        idx = torch.arange(self._sim_envs, device=self.device)
        if mask is not None and self.batch_size:
            idx = mask.reshape(self._sim_envs).nonzero().squeeze(-1)
        elif mask is not None and not bool(mask.any()):
            idx = idx[:0]
        if self._broken:  # a failed physx scene is not trusted again: rebuild it, with every env in it
            if len(idx) < self._sim_envs:
                raise RuntimeError(
                    f"the simulator failed ({self.last_sim_error}) and is rebuilt at the next reset, "
                    f"which must reset all {self._sim_envs} envs of the scene"
                )
            self._gym_env.close()
            self._gym_env = self._make_sim()
            self._broken, self.last_sim_error = False, None
        seeds = self._episode_seeds(seed, len(idx))
        if len(idx) > 0 or self._last_obs is None:
            raw_obs, info = self._sim_reset(idx, seeds)
            self._last_obs, self._last_success = self._observation(raw_obs), info.get("success")
        n = self._sim_envs
        no = torch.zeros(n, dtype=torch.bool, device=self.device)
        out = self._output(self._last_obs, torch.zeros(n), no, no, self._last_success, False)
        return out.exclude("reward")

    def _sim_reset(self, idx: Tensor, seeds: list[int] | None) -> tuple[Any, dict]:
        if len(idx) == self._sim_envs:
            options = {"reconfigure": True} if self.reconfigure_each_episode else None
            return self._gym_env.reset(
                seed=seeds if seeds is None or len(seeds) > 1 else seeds[0], options=options
            )
        if seeds is not None:
            # ManiSkill takes either one seed or one per env; keep the seeds of the envs not reset.
            current = self.sim._episode_seed
            full = np.zeros(self._sim_envs, dtype=np.int64)
            if current is not None and np.size(current) == self._sim_envs:
                full[:] = np.asarray(current, dtype=np.int64).reshape(-1)
            full[idx.cpu().numpy()] = seeds
            seeds = full.tolist()
        return self._gym_env.reset(seed=seeds, options={"env_idx": idx})

    def sim_error_message(self) -> str | None:
        """The simulator exception that ended the current episode(s), until the next reset."""
        return self.last_sim_error

    def render_frames(self) -> Tensor:
        """The render camera's RGB frame per env: uint8 [*batch, H, W, 3] on the CPU."""
        if not self.render_enabled:
            raise RuntimeError("make the env with render=True to render frames")
        return self._unsim(torch.as_tensor(self._gym_env.render())).cpu()

    def close(self, *, raise_if_closed: bool = True) -> None:
        if getattr(self, "_gym_env", None) is not None:
            self._gym_env.close()
            self._gym_env = None
        super().close(raise_if_closed=raise_if_closed)
