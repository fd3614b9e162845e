"""Where PickCube policies fail: grasp, carry, or place, episode by episode, for several checkpoints
on the same starts.

Fine-tuning plateaus on PickCube with about half the starts never solved; whether the missing
successes are grasps that never happen, cubes dropped on the way, or cubes carried to within a few
centimetres of the goal decides which exploration could reach them. Each checkpoint plays the same
episode seeds under the same noise seed; per episode it records the first grasp, the cube's highest
lift, its closest approach to the goal (success: within ``goal_thresh`` = 0.025 m and the robot
static), and whether it was still held at the end. Failures are then put in one phase each:

- ``no_grasp``: the gripper never held the cube;
- ``dropped``: held at some point, not at the end, never within 0.05 m of the goal;
- ``carried_short``: held at the end (or near the goal once) but never within 0.025 m of it;
- ``placed_not_static``: within 0.025 m at some step without the robot being static there.

    .venv/bin/python -m benchmarks.diagnose_pickcube --checkpoints start=runs/a/best.pt \\
        tuned=runs/b/best.pt --seed 100000 --episodes 100 --out benchmarks/results/x.json
"""

from __future__ import annotations

import numpy as np

from benchmarks.phase_diagnosis import diagnose
from benchmarks.rollout_states import rollout_states

#: PickCube-v1's flattened state (obs_mode=state): agent qpos (9), qvel (9), then the extras in the
#: order ``_get_obs_extra`` writes them: is_grasped (1), tcp_pose (7), goal_pos (3), obj_pose (7), ...
GRASPED, GOAL, CUBE = 18, slice(26, 29), slice(29, 32)
STATE_DIM = 42
GOAL_THRESH = 0.025
NEAR = 0.05


def play(actor, task, obs_horizon: int, seed: int, noise_seed: int) -> dict:
    """One episode from ``seed``'s start; the per-step state read back from the observation."""
    obs, first_success = rollout_states(actor, task, seed, noise_seed=noise_seed, obs_horizon=obs_horizon)
    if obs.shape[1] != STATE_DIM:
        raise ValueError(f"task {task.name}: state of size {obs.shape[1]}, expected PickCube's {STATE_DIM}")
    grasped = obs[:, GRASPED] > 0.5
    goal_dist = np.linalg.norm(obs[:, CUBE] - obs[:, GOAL], axis=1)
    lift = obs[:, CUBE][:, 2] - obs[0, CUBE][2]
    return {
        "seed": seed,
        "first_success_step": first_success,
        "first_grasp_step": int(grasped.argmax()) if grasped.any() else None,
        "held_at_end": bool(grasped[-1]),
        "max_lift": round(float(lift.max()), 3),
        "goal_dist_start": round(float(goal_dist[0]), 3),
        "goal_dist_min": round(float(goal_dist.min()), 3),
        "goal_dist_end": round(float(goal_dist[-1]), 3),
        "goal_height": round(float(obs[0, GOAL][2] - obs[0, CUBE][2]), 3),
    }


def phase(row: dict) -> str:
    """The one phase an episode ended in (see the module's docstring)."""
    if row["first_success_step"] is not None:
        return "success"
    if row["first_grasp_step"] is None:
        return "no_grasp"
    if row["goal_dist_min"] <= GOAL_THRESH:
        return "placed_not_static"
    if row["held_at_end"] or row["goal_dist_min"] <= NEAR:
        return "carried_short"
    return "dropped"


def main(argv: list[str] | None = None) -> int:
    return diagnose(
        argv,
        description=__doc__.splitlines()[0],
        env_id="PickCube-v1",
        play=play,
        phase=phase,
        constants={"goal_thresh": GOAL_THRESH},
    )


if __name__ == "__main__":
    raise SystemExit(main())
