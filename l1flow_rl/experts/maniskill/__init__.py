"""ManiSkill's own motion-planning solutions as the expert, replayed into the task's observation and
control mode with rewards (see :mod:`l1flow_rl.experts.maniskill.demos`)."""

from l1flow_rl.experts.registry import ExpertSpec, register_expert

__all__ = ["EXPERT"]


EXPERT = register_expert(
    ExpertSpec(
        simulator="maniskill",
        make="l1flow_rl.experts.maniskill.demos:ensure_maniskill_demos",
        description="ManiSkill motion planning (mani_skill.examples.motionplanning), replayed with rewards",
        options=("max_consecutive_failures", "attempt_timeout", "workers", "quality", "progress"),
    )
)
