"""The ``demos`` config group as the keyword options of the task's expert."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from l1flow_rl.experts.registry import DemoGenerationError, get_expert

__all__ = ["demo_options"]


def demo_options(cfg: DictConfig, task) -> dict:
    """The ``demos`` group's options that the task's expert takes (``num`` and ``seed`` are
    positional; the rest, e.g. ManiSkill's ``max_consecutive_failures``, only where accepted)."""
    spec = get_expert(task)
    demos = OmegaConf.to_container(cfg.demos, resolve=True)
    if demos.get("quality", "expert") != "expert" and "quality" not in spec.options:
        raise DemoGenerationError(
            f"demos.quality={demos['quality']!r}: the {spec.simulator} expert makes expert demonstrations "
            "only (mixed quality: robosuite and ManiSkill tasks)"
        )
    if demos.get("shifted_replays", 0) and "shifted_replays" not in spec.options:
        raise DemoGenerationError(
            f"demos.shifted_replays={demos['shifted_replays']}: the {spec.simulator} expert makes no shifted "
            "replays (robosuite tasks with absolute control)"
        )
    return {k: v for k, v in demos.items() if k not in ("num", "seed") and k in spec.options}
