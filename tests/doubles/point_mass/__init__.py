"""Simulator ``"point_mass"`` and its expert, registered on import: the whole of what adding a
simulator takes (this package and a task config), with no change to ``make_env``, the trainer or
the evaluator.

    import doubles.point_mass  # registers "point_mass" with both registries
    env = make_env(POINT_MASS_TASK, num_envs=2)
"""

from __future__ import annotations

import torch
from l1flow_rl.envs import SimulatorSpec, register_simulator
from torchrl.envs import EnvBase

from l1flow_rl.config import TaskConfig
from l1flow_rl.experts import ExpertSpec, register_expert

from .env import ENV_IDS, PointMassEnv

__all__ = [
    "EXPERT",
    "POINT_MASS_TASK",
    "SIMULATOR",
    "TASK_OVERRIDES",
    "TINY_BC",
    "PointMassEnv",
    "make_point_mass_env",
]

#: The task config a user would put in ``configs/task/point_mass_reach.yaml``.
POINT_MASS_TASK = TaskConfig(
    name="point_mass_reach",
    simulator="point_mass",
    env_id="PointMassReach-v0",
    obs_mode="state",
    control_mode="acceleration",
    control="absolute",
    max_episode_steps=30,
    reward_mode="normalized_dense",
)

#: The same task on the command line (``l1flow-rl train ...``, ``compose_config``).
TASK_OVERRIDES = [
    "task.name=point_mass_reach",
    "task.simulator=point_mass",
    "task.env_id=PointMassReach-v0",
    "task.control_mode=acceleration",
    "task.control=absolute",
    "task.max_episode_steps=30",
]

#: A tiny BC run on the task (``l1flow-rl train``): a start that fine-tuning tests can load in seconds.
TINY_BC = [
    "train",
    *TASK_OVERRIDES,
    "demos.num=4",
    "train.steps=30",
    "train.batch_size=16",
    "eval.enabled=false",
    "network.down_dims=[16,32]",
    "device=cpu",
]


def make_point_mass_env(
    task: TaskConfig,
    num_envs: int,
    device: torch.device,
    *,
    ignore_terminations: bool = True,
    render: bool = True,
    camera: str | None = None,
    goal_tolerance: float = 0.05,
) -> EnvBase:
    return PointMassEnv(
        task,
        num_envs,
        device,
        ignore_terminations=ignore_terminations,
        render=render,
        camera=camera,
        goal_tolerance=goal_tolerance,
    )


def _make_demos(task, num, data_dir, *, seed=0):
    from .expert import make_point_mass_demos

    return make_point_mass_demos(task, num, data_dir, seed=seed)


SIMULATOR = register_simulator(
    SimulatorSpec(
        name="point_mass",
        factory=make_point_mass_env,
        observation_entries=lambda task: {"observation": 1},
        install_hint="point_mass is a test double: import tests/doubles/point_mass (nothing to install)",
        obs_modes=("state",),
        options=("goal_tolerance",),
        env_keys=("damping",),
        episode_metrics={"final_distance": ("last", "distance")},
    )
)

EXPERT = register_expert(
    ExpertSpec(
        simulator="point_mass",
        make=_make_demos,
        description="a PD controller to the goal (robomimic-layout .hdf5)",
        env_ids=ENV_IDS,
    )
)
