"""PushT's scripted expert: a push planner that looks ahead in gym-pusht's own physics and goes
around the block on either side (see :mod:`l1flow_rl.experts.pusht.planner`); demonstrations are
Diffusion Policy zarr replay buffers (see :mod:`l1flow_rl.experts.pusht.demos`)."""

from l1flow_rl.experts.registry import ExpertSpec, register_expert

__all__ = ["EXPERT"]


EXPERT = register_expert(
    ExpertSpec(
        simulator="pusht",
        make="l1flow_rl.experts.pusht.demos:ensure_pusht_demos",
        description="PushT push planner (lookahead in gym-pusht's physics, both sides of the block)",
        env_ids=("gym_pusht/PushT-v0",),
        options=("workers", "progress", "max_failure_rate"),
    )
)
