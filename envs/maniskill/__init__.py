"""ManiSkill 3 as TorchRL envs: physx_cpu (in process, or one worker process per env) and
physx_cuda (many envs in one GPU scene). Registers simulator ``"maniskill"``; ManiSkill itself is
imported only when an env is made."""

from __future__ import annotations

import functools
from collections.abc import Mapping

import torch
from l1flow_rl.envs.maniskill.env import INSTALL_HINT, ManiSkillEnv
from l1flow_rl.envs.maniskill.protocol import PROTOCOL as PROTOCOL  # registers eval.protocol=maniskill
from l1flow_rl.envs.registry import SimulatorSpec, register_simulator
from l1flow_rl.envs.workers import ParallelWorkerEnv, check_main_guard, explain_worker_start_failure
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase

from l1flow_rl.config import TaskConfig

__all__ = [
    "CPU_BACKENDS",
    "INSTALL_HINT",
    "ManiSkillEnv",
    "make_maniskill_env",
    "maniskill_observation_entries",
]

#: make_env's ways of running several physx_cpu envs, one per worker process
CPU_BACKENDS = ("async", "parallel")


def maniskill_observation_entries(task: TaskConfig) -> Mapping[NestedKey, int]:
    if task.obs_mode == "state":
        return {"observation": 1}
    return {("observation", "state"): 1, ("observation", "rgb"): 3}


def make_maniskill_env(
    task: TaskConfig,
    num_envs: int,
    device: torch.device,
    *,
    ignore_terminations: bool = True,
    render: bool = True,
    camera: str | None = None,
    reconfigure_each_episode: bool = False,
    cpu_backend: str = "async",
) -> EnvBase:
    """The ManiSkill env of batch ``[num_envs]``: physx_cuda on a CUDA ``device``, else physx_cpu
    (``cpu_backend="async"``: gymnasium's ``AsyncVectorEnv`` workers, the faster; ``"parallel"``:
    TorchRL's ``ParallelEnv``). ``reconfigure_each_episode`` (CPU only) rebuilds the scene at each
    reset, so an episode depends on its seed alone."""
    if cpu_backend not in CPU_BACKENDS:
        raise ValueError(f"cpu_backend must be one of {CPU_BACKENDS}, got {cpu_backend!r}")
    env_kwargs = {
        "ignore_terminations": ignore_terminations,
        "render": render,
        "camera": camera,
        "reconfigure_each_episode": reconfigure_each_episode,
    }
    if device.type != "cpu":
        return ManiSkillEnv(task, num_envs=num_envs, device=device, **env_kwargs)
    if num_envs == 1:
        return ManiSkillEnv(task, num_envs=1, **env_kwargs)
    # physx_cpu holds one env per process: one unbatched env per worker, batch [num_envs] in here.
    # optional dependency: the worker envs are gymnasium's AsyncVectorEnv
    from l1flow_rl.envs.maniskill.async_env import ManiSkillAsyncEnv, use_forkserver

    if cpu_backend == "async":
        return ManiSkillAsyncEnv(task, num_envs, **env_kwargs)
    what = f"ManiSkill on the CPU with num_envs={num_envs} ({task.name!r}, cpu_backend='parallel')"
    check_main_guard(what)
    # Workers report their specs themselves, so that this process never builds a simulator.
    with explain_worker_start_failure(what):
        return ParallelWorkerEnv(
            num_envs,
            functools.partial(ManiSkillEnv, task, num_envs=None, **env_kwargs),
            mp_start_method=use_forkserver(),
            metadata_from_workers=True,
            use_buffers=False,
        )


SIMULATOR = register_simulator(
    SimulatorSpec(
        name="maniskill",
        factory=make_maniskill_env,
        observation_entries=maniskill_observation_entries,
        install_hint=INSTALL_HINT,
        requires=("mani_skill", "sapien"),
        obs_modes=("state", "rgb"),
        options=("reconfigure_each_episode", "cpu_backend"),
    )
)


def __getattr__(name: str):
    if name == "ManiSkillAsyncEnv":
        # optional dependency: the module imports gymnasium (the maniskill extra)
        from l1flow_rl.envs.maniskill.async_env import ManiSkillAsyncEnv

        return ManiSkillAsyncEnv
    raise AttributeError(f"module 'l1flow_rl.envs.maniskill' has no attribute {name!r}")
