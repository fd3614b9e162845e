"""ManiSkill's evaluation protocol (``eval.protocol=maniskill``): the settings of ManiSkill's Diffusion
Policy baseline (``examples/baselines/diffusion_policy``), so that a figure compares with its own.
Registered when the simulator package is imported; ManiSkill is imported only for a task that the
table below lacks."""

from __future__ import annotations

from typing import Any

from l1flow_rl.config import TaskConfig
from l1flow_rl.evaluation.protocols import EvalProtocol, register_protocol

__all__ = ["MANISKILL_BASELINE_STEPS", "PROTOCOL", "maniskill_baseline_steps"]

#: max_episode_steps of ManiSkill's Diffusion Policy baseline, by env id; other tasks run to the
#: env's own registered limit there
MANISKILL_BASELINE_STEPS: dict[str, int] = {
    "PushCube-v1": 100,
    "PickCube-v1": 100,
    "StackCube-v1": 200,
    "PegInsertionSide-v1": 300,
}


def maniskill_baseline_steps(task: TaskConfig) -> dict[str, Any]:
    """``max_episode_steps`` as ManiSkill's baseline sets it for ``task.env_id``: the table above,
    else the env's registered default."""
    steps = MANISKILL_BASELINE_STEPS.get(task.env_id)
    if steps is None:
        # optional dependency: the simulator, only for an env id the table lacks
        import gymnasium as gym
        import mani_skill.envs  # noqa: F401  (registers the env ids)

        try:
            steps = gym.spec(task.env_id).max_episode_steps
        except gym.error.Error as err:
            raise ValueError(f"eval.protocol=maniskill: unknown ManiSkill env id {task.env_id!r}") from err
        if steps is None:
            raise ValueError(f"eval.protocol=maniskill: {task.env_id!r} registers no max_episode_steps")
    return {"max_episode_steps": int(steps)}


PROTOCOL = register_protocol(
    EvalProtocol(
        name="maniskill",
        description=(
            "ManiSkill's Diffusion Policy baseline: its per-task max_episode_steps, 100 episodes, "
            "physx_cpu, scene reconfigured each episode, success_once first"
        ),
        episodes=100,
        task_fields=maniskill_baseline_steps,
        env_options={"reconfigure_each_episode": True},
        env_device="cpu",
        headline="success_once",
        simulators=("maniskill",),
    ),
    replace=True,  # a re-imported module registers its own copy
)
