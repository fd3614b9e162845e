"""Scripted robosuite experts (Lift, Stack, PickPlaceCan, NutAssemblySquare, ToolHang) writing robomimic
files; see :mod:`l1flow_rl.experts.robosuite.demos`. Imports no simulator until demonstrations are made."""

from l1flow_rl.experts.registry import ExpertSpec, register_expert

__all__ = ["EXPERT"]


EXPERT = register_expert(
    ExpertSpec(
        simulator="robosuite",
        make="l1flow_rl.experts.robosuite.demos:ensure_robosuite_demos",
        description="scripted pick-and-place on privileged state (randomised speed, grasp offset, waypoints)",
        env_ids=("Lift", "Stack", "PickPlaceCan", "NutAssemblySquare", "ToolHang"),
        options=("workers", "max_consecutive_failures", "quality", "shifted_replays", "progress"),
    )
)
