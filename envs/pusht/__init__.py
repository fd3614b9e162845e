"""PushT (gym-pusht's ``gym_pusht/PushT-v0``) as TorchRL envs. Registers simulator ``"pusht"`` with
Diffusion Policy's per-episode score; gym-pusht is imported only when an env is made.

    from l1flow_rl.envs import make_env
    env = make_env("pusht", num_envs=2)    # 2 worker processes, keypoint observations [2, To, 20]
"""

from __future__ import annotations

import functools
from collections.abc import Mapping

import torch
from l1flow_rl.envs.pusht.env import PushTEnv
from l1flow_rl.envs.pusht.protocol import PROTOCOL as PROTOCOL  # registers eval.protocol=diffusion_policy
from l1flow_rl.envs.registry import SimulatorSpec, register_simulator
from l1flow_rl.envs.workers import (
    ParallelWorkerEnv,
    SerialWorkerEnv,
    check_main_guard,
    explain_worker_start_failure,
    signal_safe_factory,
)
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase

from l1flow_rl.config import TaskConfig

__all__ = ["BACKENDS", "INSTALL_HINT", "PushTEnv", "make_pusht_env", "pusht_observation_entries"]

INSTALL_HINT = "pip install 'l1flow-rl[pusht]' (or: pip install gym-pusht==0.1.8)"

#: how make_env runs several PushT envs: worker processes (``parallel``), one after another in this
#: process (``serial``), or ``auto``: serial for the low-dim modes, whose steps are so cheap that
#: TorchRL's inter-process overhead is the bottleneck (serial and parallel against raw gym-pusht:
#: benchmarks/results/pusht_env.json), parallel for the pixel modes
BACKENDS = ("auto", "parallel", "serial")

#: TaskConfig.obs_mode values (see l1flow_rl.envs.pusht.env.OBS_MODES)
PUSHT_OBS_MODES = ("state", "keypoints", "environment_state_agent_pos", "pixels", "pixels_agent_pos")


def pusht_observation_entries(task: TaskConfig) -> Mapping[NestedKey, int]:
    if task.obs_mode == "pixels":
        return {("observation", "rgb"): 3}
    if task.obs_mode == "pixels_agent_pos":
        return {("observation", "state"): 1, ("observation", "rgb"): 3}
    return {"observation": 1}


def pusht_reader_options(task: TaskConfig) -> Mapping:
    """What selects a task's observation from a Diffusion Policy zarr file: ``task.state_keys``
    (``keypoint``, ``agent_pos`` = ``data/state[:, :2]``, ``state``) and, for the image tasks, the
    images (``task.cameras``, default ``img``)."""
    options = {"state_keys": list(task.state_keys) or ["state"]}
    if task.obs_mode in ("pixels", "pixels_agent_pos"):
        options["image_key"] = (list(task.cameras) or ["img"])[0]
        if task.obs_mode == "pixels":
            options["state_keys"] = []
    else:
        options["image_key"] = None
    return options


def make_pusht_env(
    task: TaskConfig,
    num_envs: int,
    device: torch.device,
    *,
    ignore_terminations: bool = True,
    render: bool = True,
    camera: str | None = None,
    backend: str = "auto",
    mp_start_method: str = "spawn",
) -> EnvBase:
    """PushT envs of batch ``[num_envs]``: one :class:`~l1flow_rl.envs.pusht.env.PushTEnv` per worker
    process (``backend="parallel"``, a single env stays in this process) or all in this process
    (``"serial"``); ``"auto"`` picks serial for low-dim observations and parallel for pixels. The
    simulator runs on the CPU; outputs move to ``device``. Workers are spawned: forked ones hung at
    their first reset here (a script that makes them needs the ``__main__`` guard)."""
    if backend not in BACKENDS:
        raise ValueError(f"pusht: backend must be one of {BACKENDS}, got {backend!r}")
    make = functools.partial(
        PushTEnv, task, ignore_terminations=ignore_terminations, render=render, camera=camera
    )
    if backend == "auto":
        backend = "parallel" if task.obs_mode in ("pixels", "pixels_agent_pos") else "serial"
    if backend == "serial" or num_envs == 1:
        env = SerialWorkerEnv(num_envs, make, device=device)
    else:
        what = f"PushT with num_envs={num_envs} in worker processes ({task.name!r})"
        check_main_guard(what)  # spawned workers re-import the main script
        with explain_worker_start_failure(what):
            env = ParallelWorkerEnv(
                num_envs, signal_safe_factory(make), mp_start_method=mp_start_method, device=device
            )
    return env


SIMULATOR = register_simulator(
    SimulatorSpec(
        name="pusht",
        factory=make_pusht_env,
        observation_entries=pusht_observation_entries,
        install_hint=INSTALL_HINT,
        requires=("gym_pusht", "pymunk", "pygame"),
        obs_modes=PUSHT_OBS_MODES,
        options=("backend", "mp_start_method"),
        env_keys=(),
        reader_options=pusht_reader_options,
        # Diffusion Policy's PushT metric: an episode's score is its best clip(coverage / 0.95, 0, 1)
        episode_metrics={"score": ("max", "reward"), "max_coverage": ("max", "coverage")},
    )
)
