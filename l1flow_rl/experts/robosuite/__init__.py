"""Scripted robosuite experts (Lift, Stack, PickPlaceCan) writing robomimic files; see
:mod:`l1flow_rl.experts.robosuite.demos`. Imports no simulator until demonstrations are made."""

from l1flow_rl.experts.registry import ExpertSpec, register_expert

__all__ = ["EXPERT"]


def _make(task, num, data_dir, *, seed=0, **options):
    from l1flow_rl.experts.robosuite.demos import ensure_robosuite_demos

    return ensure_robosuite_demos(task, num, data_dir, seed=seed, **options)


EXPERT = register_expert(
    ExpertSpec(
        simulator="robosuite",
        make=_make,
        description="scripted pick-and-place on privileged state (randomised speed, grasp offset, waypoints)",
        env_ids=("Lift", "Stack", "PickPlaceCan"),
        options=("workers", "max_consecutive_failures", "progress"),
    )
)
