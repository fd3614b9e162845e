"""Structured config schemas. Hydra merges YAML from ``configs/`` onto these, so a wrong key or a
value of the wrong type fails before any work starts, with the offending key in the message."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import OmegaConf

__all__ = ["CONFIG_DIR", "TaskConfig", "load_task_config", "task_names"]

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
if not (CONFIG_DIR / "task").is_dir():  # installed (non-editable): configs ship as l1flow_rl.configs
    CONFIG_DIR = Path(__file__).resolve().parent / "configs"


@dataclass
class TaskConfig:
    """One simulator task: what to make, observe and control, and how long an episode may run."""

    name: str = "maniskill_pushcube"
    simulator: str = "maniskill"  # maniskill | robosuite | pusht
    env_id: str = "PushCube-v1"
    obs_mode: str = "state"  # state | rgb
    control_mode: str = "pd_ee_delta_pos"
    max_episode_steps: int = 100
    reward_mode: str = "normalized_dense"
    # Delta control pads chunks past an episode's end with zero arm motion (and the last gripper
    # command); absolute control repeats the last action.
    delta_control: bool = True
    image_size: int = 128
    env_kwargs: dict = field(default_factory=dict)


def task_names() -> list[str]:
    return sorted(p.stem for p in (CONFIG_DIR / "task").glob("*.yaml"))


def load_task_config(name: str, **overrides) -> TaskConfig:
    """Task config by name (a file in ``configs/task``), validated against :class:`TaskConfig`."""
    path = CONFIG_DIR / "task" / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"unknown task {name!r}; known tasks: {task_names()}")
    cfg = OmegaConf.merge(OmegaConf.structured(TaskConfig), OmegaConf.load(path), overrides)
    return OmegaConf.to_object(cfg)  # type: ignore[return-value]
