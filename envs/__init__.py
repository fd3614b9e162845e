"""Simulator adapters: tasks as TorchRL environments. Simulators are imported only when an env is made.

from l1flow_rl.envs import make_env
env = make_env("maniskill_pushcube", num_envs=2)   # 2 physx_cpu worker processes
"""

from l1flow_rl.envs.factory import history_transforms, make_env, resolve_device
from l1flow_rl.envs.maniskill_obs import flatten_maniskill_obs

__all__ = [
    "ManiSkillAsyncEnv",
    "ManiSkillEnv",
    "flatten_maniskill_obs",
    "history_transforms",
    "make_env",
    "resolve_device",
]


def __getattr__(name: str):
    # lazy: keep the package import minimal (the async module imports gymnasium)
    if name == "ManiSkillEnv":
        from l1flow_rl.envs.maniskill_env import ManiSkillEnv

        return ManiSkillEnv
    if name == "ManiSkillAsyncEnv":
        from l1flow_rl.envs.maniskill_async import ManiSkillAsyncEnv

        return ManiSkillAsyncEnv
    raise AttributeError(f"module 'l1flow_rl.envs' has no attribute {name!r}")
