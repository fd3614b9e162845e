"""robosuite 1.5 (robomimic's and MimicGen's simulator) as TorchRL envs. Registers simulator
``"robosuite"``; robosuite itself is imported only when an env is made.

Observations use robomimic's keys (``object``, ``robot0_eef_pos``, ``robot0_eef_quat``,
``robot0_gripper_qpos``, ..., and ``<camera>_image``), the controller is OSC with absolute or delta
actions as the task says, and success is the env's own ``_check_success()``.
"""

from __future__ import annotations

import functools
import multiprocessing
from collections.abc import Mapping

import torch
from l1flow_rl.envs.registry import SimulatorSpec, register_simulator
from l1flow_rl.envs.robosuite.dataset import prepare_robomimic_dataset, robosuite_reader_options
from l1flow_rl.envs.robosuite.env import RobosuiteEnv
from l1flow_rl.envs.robosuite.pool import forkserver
from l1flow_rl.envs.robosuite.sim import INSTALL_HINT, image_key
from l1flow_rl.envs.workers import ParallelWorkerEnv, SerialWorkerEnv
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase

from l1flow_rl.config import TaskConfig

__all__ = ["INSTALL_HINT", "RobosuiteEnv", "make_robosuite_env", "robosuite_observation_entries"]


def robosuite_observation_entries(task: TaskConfig) -> Mapping[NestedKey, int]:
    if task.obs_mode == "state":
        return {"observation": 1}
    return {("observation", "state"): 1, **{("observation", image_key(c)): 3 for c in task.cameras}}


def _worker_env(task: TaskConfig, **kwargs) -> EnvBase:
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
        env = SerialWorkerEnv(1, make)
    else:
        env = ParallelWorkerEnv(num_envs, make, mp_start_method=forkserver())
    return env.to(device) if device.type != "cpu" else env


SIMULATOR = register_simulator(
    SimulatorSpec(
        name="robosuite",
        factory=make_robosuite_env,
        observation_entries=robosuite_observation_entries,
        install_hint=INSTALL_HINT,
        requires=("robosuite", "mujoco"),
        obs_modes=("state", "rgb"),
        prepare_dataset=prepare_robomimic_dataset,
        reader_options=robosuite_reader_options,
    )
)
