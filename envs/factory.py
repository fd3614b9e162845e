"""``make_env``: a task config name in, a TorchRL env with observation history out."""

from __future__ import annotations

import dataclasses
import functools

import torch
from torchrl.envs import (
    CatFrames,
    Compose,
    EnvBase,
    InitTracker,
    ParallelEnv,
    TransformedEnv,
    UnsqueezeTransform,
)

from l1flow_rl.config import TaskConfig, load_task_config

__all__ = ["CPU_BACKENDS", "history_transforms", "make_env", "resolve_device"]

#: observation entry -> the dim of one frame's [C, H, W] or [D] that history is stacked in front of
_FRAME_DIMS = {"state": -2, "rgb": -4}


def history_transforms(obs_mode: str, obs_horizon: int) -> Compose:
    """``InitTracker`` ("is_init", for ``MultiStepActorWrapper``) and a stack of the last
    ``obs_horizon`` observations, padded at reset with copies of the first one.

    state: ``"observation"`` [*B, D] -> [*B, To, D];
    rgb: ``("observation", "state")`` [*B, D] -> [*B, To, D] and ``("observation", "rgb")``
    [*B, 3, H, W] -> [*B, To, 3, H, W].
    """
    if obs_horizon < 1:
        raise ValueError(f"obs_horizon must be >= 1, got {obs_horizon}")
    if obs_mode == "state":
        entries = {"observation": _FRAME_DIMS["state"]}
    elif obs_mode == "rgb":
        entries = {("observation", name): dim for name, dim in _FRAME_DIMS.items()}
    else:
        raise ValueError(f"obs_mode must be 'state' or 'rgb', got {obs_mode!r}")
    transforms = [InitTracker()]
    for key, dim in entries.items():
        transforms.append(UnsqueezeTransform(dim, in_keys=[key]))
        transforms.append(CatFrames(N=obs_horizon, dim=dim, in_keys=[key]))
    return Compose(*transforms)


def resolve_device(device: str | torch.device) -> torch.device:
    """``"auto"`` -> CUDA when present, else CPU; a CUDA device that is absent is an error."""
    if str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device={device} was asked for, but torch sees no CUDA device")
    return device


#: make_env's ways of running several physx_cpu envs, one per worker process
CPU_BACKENDS = ("async", "parallel")


def _maniskill_base(
    task: TaskConfig, num_envs: int, device: torch.device, cpu_backend: str, **env_kwargs
) -> EnvBase:
    from l1flow_rl.envs.maniskill_env import ManiSkillEnv

    if device.type != "cpu":
        return ManiSkillEnv(task, num_envs=num_envs, device=device, **env_kwargs)
    if num_envs == 1:
        return ManiSkillEnv(task, num_envs=1, **env_kwargs)
    # physx_cpu holds one env per process: one unbatched env per worker, batch [num_envs] in here.
    from l1flow_rl.envs.maniskill_async import ManiSkillAsyncEnv, use_forkserver

    if cpu_backend == "async":
        return ManiSkillAsyncEnv(task, num_envs, **env_kwargs)
    # Workers report their specs themselves, so that this process never builds a simulator.
    return ParallelEnv(
        num_envs,
        functools.partial(ManiSkillEnv, task, num_envs=None, **env_kwargs),
        mp_start_method=use_forkserver(),
        metadata_from_workers=True,
        use_buffers=False,
    )


def make_env(
    task: str | TaskConfig,
    num_envs: int = 1,
    device: str | torch.device = "cpu",
    *,
    obs_horizon: int = 2,
    ignore_terminations: bool = True,
    render: bool = True,
    camera: str | None = None,
    reconfigure_each_episode: bool = False,
    cpu_backend: str = "async",
    **overrides,
) -> TransformedEnv:
    """The TorchRL env of a task, batch size ``[num_envs]``, with observation history.

    Args:
        task: a task config name (a file in ``configs/task``) or a :class:`TaskConfig`.
        num_envs: parallel envs. CPU: that many worker processes (one env each, started through
            multiprocessing's forkserver, so a script that makes one needs the
            ``if __name__ == "__main__":`` guard); CUDA: one ManiSkill physx_cuda scene with that
            many envs in this process.
        device: ``"cpu"``, ``"cuda"``/``"cuda:k"`` or ``"auto"``.
        obs_horizon: To, the number of stacked observations.
        ignore_terminations: ManiSkill's evaluation setting: run every episode to the time limit.
        render: allow ``render_frames()`` (videos); costs nothing measurable until a frame is asked for.
        camera: which camera feeds ``"rgb"`` when the task has several.
        reconfigure_each_episode: CPU only: rebuild the scene at each reset, so that an episode
            depends on its seed alone and not on the episodes before it (see ``ManiSkillEnv``).
        cpu_backend: how CPU workers run when ``num_envs > 1``: ``"async"`` (gymnasium's
            ``AsyncVectorEnv`` under :class:`~l1flow_rl.envs.maniskill_async.ManiSkillAsyncEnv`,
            the faster) or ``"parallel"`` (TorchRL's ``ParallelEnv``).
        overrides: task config fields, e.g. ``max_episode_steps=50``.

    Example:
        >>> env = make_env("maniskill_pushcube", max_episode_steps=20)
        >>> env.reset()["observation"].shape
        torch.Size([1, 2, 35])
    """
    if isinstance(task, TaskConfig):
        cfg = dataclasses.replace(task, **overrides) if overrides else task
    else:
        cfg = load_task_config(task, **overrides)
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    if cpu_backend not in CPU_BACKENDS:
        raise ValueError(f"cpu_backend must be one of {CPU_BACKENDS}, got {cpu_backend!r}")
    env_kwargs = {
        "ignore_terminations": ignore_terminations,
        "render": render,
        "camera": camera,
        "reconfigure_each_episode": reconfigure_each_episode,
    }
    if cfg.simulator == "maniskill":
        base = _maniskill_base(cfg, num_envs, resolve_device(device), cpu_backend, **env_kwargs)
    else:
        raise NotImplementedError(
            f"task {cfg.name!r}: make_env has no adapter for simulator {cfg.simulator!r} (has: 'maniskill')"
        )
    return TransformedEnv(base, history_transforms(cfg.obs_mode, obs_horizon))
