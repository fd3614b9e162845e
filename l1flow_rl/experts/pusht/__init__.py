"""PushT's scripted expert: a push planner that looks ahead in gym-pusht's own physics and goes
around the block on either side (see :mod:`l1flow_rl.experts.pusht.planner`); demonstrations are
Diffusion Policy zarr replay buffers (see :mod:`l1flow_rl.experts.pusht.demos`)."""

from l1flow_rl.experts.registry import ExpertSpec, register_expert

__all__ = ["EXPERT"]


def _make(task, num, data_dir, *, seed=0, **options):
    from l1flow_rl.experts.pusht.demos import ensure_pusht_demos

    return ensure_pusht_demos(task, num, data_dir, seed=seed, **options)


EXPERT = register_expert(
    ExpertSpec(
        simulator="pusht",
        make=_make,
        description="PushT push planner (lookahead in gym-pusht's physics, both sides of the block)",
        env_ids=("gym_pusht/PushT-v0",),
        options=("workers", "progress", "max_failure_rate"),
    )
)
