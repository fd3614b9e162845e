"""The task group (``configs/task/*.yaml``): which simulator, which env, what it observes and how it
is controlled. Simulator-specific options live in the ``env`` block, read only by that simulator's
factory (``l1flow_rl.envs``), and expert options in the ``expert`` block."""

from __future__ import annotations

from dataclasses import dataclass, field

from omegaconf import OmegaConf

from l1flow_rl.config.paths import CONFIG_DIR
from l1flow_rl.config.ranges import bounded

__all__ = ["CONTROL_KINDS", "TaskConfig", "load_task_config", "task_names"]

#: what an action means: a change from the current pose (``delta``) or a target (``absolute``)
CONTROL_KINDS = ("delta", "absolute")


@dataclass
class TaskConfig:
    """One simulator task: what to make, observe and control, and how long an episode may run."""

    name: str = "maniskill_pushcube"
    simulator: str = "maniskill"  # a registered simulator: l1flow_rl.envs.registered_simulators()
    env_id: str = "PushCube-v1"
    obs_mode: str = "state"  # state | rgb | a simulator's own modes (pusht: keypoints, pixels, ...)
    # The simulator's controller name (ManiSkill pd_ee_delta_pos, robosuite OSC_POSE, ...); the
    # recorded control mode of a dataset must match it.
    control_mode: str = "pd_ee_delta_pos"
    # delta | absolute. Decides how chunks are padded past an episode's end (delta: zero motion and
    # the last gripper command; absolute: repeat the last action); checked against the data's record.
    control: str = "delta"
    max_episode_steps: int = bounded(100, ge=1)
    reward_mode: str = "normalized_dense"
    image_size: int = bounded(128, ge=1)
    # Low-dimensional entries that form the "state" observation, in order (robosuite: robomimic's
    # keys); empty means the simulator's default state.
    state_keys: list[str] = field(default_factory=list)
    # Cameras that become image entries (uint8 [3, H, W] each); empty means the simulator's default.
    cameras: list[str] = field(default_factory=list)
    env: dict = field(default_factory=dict)  # simulator-specific env options
    expert: dict = field(default_factory=dict)  # demonstration-source options (l1flow_rl.experts)


def task_names() -> list[str]:
    return sorted(p.stem for p in (CONFIG_DIR / "task").glob("*.yaml"))


def load_task_config(name: str, **overrides) -> TaskConfig:
    """Task config by name (a file in ``configs/task``), validated against :class:`TaskConfig`."""
    path = CONFIG_DIR / "task" / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"unknown task {name!r}; known tasks: {task_names()}")
    raw = OmegaConf.load(path)
    raw.pop("defaults", None)  # hydra's defaults list (a task's default train budget), not a task field
    cfg = OmegaConf.merge(OmegaConf.structured(TaskConfig), raw, overrides)
    return OmegaConf.to_object(cfg)  # type: ignore[return-value]
