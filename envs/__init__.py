"""Simulator adapters: tasks as TorchRL environments. Simulators are imported only when an env is made.

from l1flow_rl.envs import make_env
env = make_env("maniskill_pushcube", num_envs=2)   # ParallelEnv of 2 physx_cpu workers
"""

from l1flow_rl.envs.factory import history_transforms, make_env, resolve_device
from l1flow_rl.envs.maniskill_obs import flatten_maniskill_obs

__all__ = ["ManiSkillEnv", "flatten_maniskill_obs", "history_transforms", "make_env", "resolve_device"]


def __getattr__(name: str):
    if name == "ManiSkillEnv":  # lazy: the adapter module is cheap, but keep the package import minimal
        from l1flow_rl.envs.maniskill_env import ManiSkillEnv

        return ManiSkillEnv
    raise AttributeError(f"module 'l1flow_rl.envs' has no attribute {name!r}")
