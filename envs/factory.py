"""``make_env``: a task config name in, a TorchRL env with observation history out."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import torch
from l1flow_rl.envs.registry import get_simulator
from tensordict.utils import NestedKey
from torchrl.envs import CatFrames, Compose, InitTracker, TransformedEnv, UnsqueezeTransform

from l1flow_rl.config import TaskConfig, load_task_config
from l1flow_rl.utils.device import resolve_device

__all__ = ["history_transforms", "make_env", "resolve_device"]


def history_transforms(entries: Mapping[NestedKey, int], obs_horizon: int) -> Compose:
    """``InitTracker`` ("is_init", for ``MultiStepActorWrapper``) and a stack of the last
    ``obs_horizon`` frames of each observation entry, padded at reset with copies of the first one.

    ``entries`` maps an entry to the number of dims of one frame (the simulator's
    ``observation_entries``): ``{"observation": 1}`` turns [*B, D] into [*B, To, D];
    ``{("observation", "rgb"): 3}`` turns [*B, 3, H, W] into [*B, To, 3, H, W].
    """
    if obs_horizon < 1:
        raise ValueError(f"obs_horizon must be >= 1, got {obs_horizon}")
    transforms = [InitTracker()]
    for key, frame_dims in entries.items():
        dim = -(int(frame_dims) + 1)
        transforms.append(UnsqueezeTransform(dim, in_keys=[key]))
        transforms.append(CatFrames(N=obs_horizon, dim=dim, in_keys=[key]))
    return Compose(*transforms)


def make_env(
    task: str | TaskConfig,
    num_envs: int = 1,
    device: str | torch.device = "cpu",
    *,
    obs_horizon: int = 2,
    ignore_terminations: bool = True,
    render: bool = True,
    camera: str | None = None,
    **options: Any,
) -> TransformedEnv:
    """The TorchRL env of a task, batch size ``[num_envs]``, with observation history.

    The task's simulator (``TaskConfig.simulator``) is looked up in :mod:`l1flow_rl.envs.registry`;
    its factory makes the env from the task, and the history transforms stack the entries that the
    simulator declares.

    Args:
        task: a task config name (a file in ``configs/task``) or a :class:`TaskConfig`.
        num_envs: parallel envs. On the CPU most simulators run them in worker processes: a
            script that makes them needs the ``if __name__ == "__main__":`` guard, and is told so
            (:func:`l1flow_rl.envs.workers.check_main_guard`) before any worker starts. ManiSkill
            on CUDA runs one physx_cuda scene with that many envs in this process.
        device: ``"cpu"``, ``"cuda"``/``"cuda:k"`` or ``"auto"``.
        obs_horizon: To, the number of stacked observations.
        ignore_terminations: ManiSkill's evaluation setting: run every episode to the time limit.
        render: allow ``render_frames()`` (videos); costs nothing measurable until a frame is asked for.
        camera: which camera feeds the image entry when the task has several.
        **options: the simulator's own options (``SimulatorSpec.options``; ManiSkill:
            ``reconfigure_each_episode``, ``cpu_backend``), then task config fields, e.g.
            ``max_episode_steps=50``. Anything else is refused, naming it, before an env is built;
            so are a missing simulator (with its install hint) and an obs_mode it lacks.

    Example:
        >>> env = make_env("maniskill_pushcube", max_episode_steps=20)
        >>> env.reset()["observation"].shape
        torch.Size([1, 2, 35])
    """
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    task_fields = {f.name for f in dataclasses.fields(TaskConfig)}
    overrides = {k: v for k, v in options.items() if k in task_fields}
    sim_options = {k: v for k, v in options.items() if k not in task_fields}
    if isinstance(task, TaskConfig):
        cfg = dataclasses.replace(task, **overrides) if overrides else task
    else:
        cfg = load_task_config(task, **overrides)
    sim = get_simulator(cfg.simulator)
    unknown = sorted(set(sim_options) - set(sim.options))
    if unknown:
        raise TypeError(
            f"make_env: {unknown} are neither TaskConfig fields nor options of simulator "
            f"{sim.name!r} (its options: {list(sim.options)})"
        )
    base = sim.make(
        cfg,
        num_envs,
        resolve_device(device),
        ignore_terminations=ignore_terminations,
        render=render,
        camera=camera,
        **sim_options,
    )
    return TransformedEnv(base, history_transforms(sim.observation_entries(cfg), obs_horizon))
