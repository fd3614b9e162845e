"""Simulator adapters: tasks as TorchRL environments, found through a registry
(:mod:`l1flow_rl.envs.registry`). Simulators are imported only when an env is made.

from l1flow_rl.envs import make_env
env = make_env("maniskill_pushcube", num_envs=2)   # 2 physx_cpu worker processes
"""

from l1flow_rl.envs.factory import history_transforms, make_env, resolve_device
from l1flow_rl.envs.registry import (
    SimulatorNotInstalledError,
    SimulatorSpec,
    get_simulator,
    register_simulator,
    registered_simulators,
    unregister_simulator,
)

__all__ = [
    "ManiSkillAsyncEnv",
    "ManiSkillEnv",
    "SimulatorNotInstalledError",
    "SimulatorSpec",
    "flatten_maniskill_obs",
    "get_simulator",
    "history_transforms",
    "make_env",
    "register_simulator",
    "registered_simulators",
    "resolve_device",
    "unregister_simulator",
]


def __getattr__(name: str):
    # lazy: keep the package import minimal (these modules import gymnasium and ManiSkill's helpers)
    if name in ("ManiSkillEnv", "ManiSkillAsyncEnv"):
        from l1flow_rl.envs import maniskill

        return getattr(maniskill, name)
    if name == "flatten_maniskill_obs":
        from l1flow_rl.envs.maniskill.obs import flatten_maniskill_obs

        return flatten_maniskill_obs
    raise AttributeError(f"module 'l1flow_rl.envs' has no attribute {name!r}")
