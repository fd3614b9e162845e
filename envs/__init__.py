"""Simulator adapters: tasks as TorchRL environments, found through a registry
(:mod:`l1flow_rl.envs.registry`). Simulators are imported only when an env is made; each simulator's
own classes live in its package (``l1flow_rl.envs.maniskill``, ...).

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
    "SimulatorNotInstalledError",
    "SimulatorSpec",
    "get_simulator",
    "history_transforms",
    "make_env",
    "register_simulator",
    "registered_simulators",
    "resolve_device",
    "unregister_simulator",
]
