"""robosuite 1.5 (robomimic's and MimicGen's simulator) as TorchRL envs. Registers simulator
``"robosuite"``; robosuite itself is imported only when an env is made.

Observations use robomimic's keys (``object``, ``robot0_eef_pos``, ``robot0_eef_quat``,
``robot0_gripper_qpos``, ..., and ``<camera>_image``), the controller is OSC with absolute or delta
actions as the task says, and success is the env's own ``_check_success()``.
"""

from __future__ import annotations

import functools
import multiprocessing
import os
from collections.abc import Mapping

import torch
from l1flow_rl.envs.registry import SimulatorSpec, register_simulator
from l1flow_rl.envs.robosuite.sim import INSTALL_HINT, image_key
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase, ParallelEnv, SerialEnv

from l1flow_rl.config import TaskConfig

__all__ = ["INSTALL_HINT", "RobosuiteEnv", "make_robosuite_env", "robosuite_observation_entries"]

#: imported once by the forkserver, so each worker forks with robosuite already imported (~3 s each)
_WORKER_PRELOAD = ["torch", "torchrl.envs", "robosuite", "l1flow_rl.envs.robosuite.env"]


def robosuite_observation_entries(task: TaskConfig) -> Mapping[NestedKey, int]:
    if task.obs_mode == "state":
        return {"observation": 1}
    return {("observation", "state"): 1, **{("observation", image_key(c)): 3 for c in task.cameras}}


def _forkserver() -> str:
    from l1flow_rl.envs.robosuite.sim import _choose_gl

    os.environ.setdefault("MUJOCO_GL", _choose_gl())  # the server reads it when it imports robosuite
    multiprocessing.set_forkserver_preload(_WORKER_PRELOAD)
    return "forkserver"


def _worker_env(task: TaskConfig, **kwargs) -> EnvBase:
    from l1flow_rl.envs.robosuite.env import RobosuiteEnv

    if multiprocessing.parent_process() is not None:
        torch.set_num_threads(1)  # the workers already use every core
    return RobosuiteEnv(task, **kwargs)


def make_robosuite_env(
    task: TaskConfig,
    num_envs: int,
    device: torch.device,
    *,
    ignore_terminations: bool = True,
    render: bool = True,
    camera: str | None = None,
) -> EnvBase:
    """``num_envs`` robosuite envs as one TorchRL env of batch ``[num_envs]``: one in this process
    (``SerialEnv``), or one per worker process (``ParallelEnv``; scripts need the ``__main__``
    guard). MuJoCo runs on the CPU; with a CUDA ``device`` the outputs are moved there."""
    make = functools.partial(
        _worker_env, task, ignore_terminations=ignore_terminations, render=render, camera=camera
    )
    if num_envs == 1:
        env = SerialEnv(1, make)
    else:
        env = ParallelEnv(num_envs, make, mp_start_method=_forkserver())
    return env.to(device) if device.type != "cpu" else env


def _prepare_dataset(task: TaskConfig, path, data_dir):
    from l1flow_rl.envs.robosuite.dataset import prepare_robomimic_dataset

    return prepare_robomimic_dataset(task, path, data_dir)


def _reader_options(task: TaskConfig) -> Mapping:
    from l1flow_rl.envs.robosuite.dataset import robosuite_reader_options

    return robosuite_reader_options(task)


SIMULATOR = register_simulator(
    SimulatorSpec(
        name="robosuite",
        factory=make_robosuite_env,
        observation_entries=robosuite_observation_entries,
        install_hint=INSTALL_HINT,
        requires=("robosuite", "mujoco"),
        obs_modes=("state", "rgb"),
        prepare_dataset=_prepare_dataset,
        reader_options=_reader_options,
    )
)


def __getattr__(name: str):
    if name == "RobosuiteEnv":
        from l1flow_rl.envs.robosuite.env import RobosuiteEnv

        return RobosuiteEnv
    raise AttributeError(f"module 'l1flow_rl.envs.robosuite' has no attribute {name!r}")
