"""PushT's evaluation protocol (``eval.protocol=diffusion_policy``): Diffusion Policy's PushT
evaluation, registered when the simulator package is imported."""

from __future__ import annotations

from l1flow_rl.evaluation.protocols import EvalProtocol, register_protocol

__all__ = ["PROTOCOL"]

PROTOCOL = register_protocol(
    EvalProtocol(
        name="diffusion_policy",
        description=(
            "Diffusion Policy's PushT evaluation: 50 test seeds from 100000, 300 steps, score (the "
            "mean of each episode's best clip(coverage / 0.95, 0, 1)) first"
        ),
        episodes=50,
        seed=100000,
        task_fields=lambda task: {"max_episode_steps": 300},
        headline="score",
        simulators=("pusht",),
    ),
    replace=True,  # a re-imported module registers its own copy
)
