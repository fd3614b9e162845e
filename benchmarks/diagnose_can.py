"""Where robosuite Can policies fail: reach and lift, carry, or place in the bin, episode by
episode, for several checkpoints on the same starts.

Filtered BC adds ~+11 on Can's mixed-quality start where it adds +36 on PickCube; PickCube's
failures were cubes parked just outside the goal (a labelling artefact of delta control's padding),
and Can's absolute control pads with a true label, so its failures must be read before any new arm.
Per episode it records the can's highest lift, the first step it is lifted, the hand's closest
approach to it (in 3-D, and sideways with the hand's height there), how far the can was pushed,
whether it is still held at the end, and when it first sits over the target bin.
Failures are put in one phase each:

- ``no_lift``: the can never rose ``LIFT`` above its start (a missed or never-tried grasp);
- ``over_bin_not_placed``: it was over the target bin at some step and never counted as in it;
- ``carried_not_over_bin``: held at the end, never over the bin (too slow, or lost its way);
- ``dropped``: lifted, then let go before it ever reached the bin.

    .venv/bin/python -m benchmarks.diagnose_can --checkpoints start=runs/a/best.pt \\
        tuned=runs/b/best.pt --seed 100000 --episodes 100 --out benchmarks/results/x.json
"""

from __future__ import annotations

import numpy as np

from benchmarks.phase_diagnosis import diagnose
from benchmarks.rollout_states import rollout_states

#: The Can task's state (``state_keys: [object, robot0_eef_pos, robot0_eef_quat,
#: robot0_gripper_qpos]``): object = [Can_to_robot0_eef_pos 3, ..._quat 4, Can_pos 3, Can_quat 4].
CAN, EEF = slice(7, 10), slice(14, 17)
FINGERS = slice(21, 23)  # robot0_gripper_qpos: the two finger joints (+, -); their difference is the opening
STATE_DIM = 23
#: PickPlace's bin for the can (bin id 3): x in bin2_x + [0, 0.39/2], y in bin2_y + [0, 0.49/2],
#: read from robosuite's ``not_in_bin`` with its defaults bin2_pos (0.1, 0.28, 0.8), bin_size (0.39, 0.49)
BIN_X, BIN_Y = (0.1, 0.295), (0.28, 0.525)
LIFT = 0.03
HOLD = 0.04  # hand-to-can centre distance that counts as holding (the can's radius is ~0.03)


def first_close(obs: np.ndarray) -> tuple[int | None, list[float] | None]:
    """The first step the fingers have closed by 5 mm from their widest so far (the first grasp), and
    the hand's x, y offset from the can there (None, None: they never closed)."""
    opening = obs[:, FINGERS][:, 0] - obs[:, FINGERS][:, 1]
    closed = np.flatnonzero(opening < np.maximum.accumulate(opening) - 0.005)
    if not closed.size:
        return None, None
    step = int(closed[0])
    return step, [round(float(v), 4) for v in obs[step, EEF][:2] - obs[step, CAN][:2]]


def play(actor, task, obs_horizon: int, seed: int, noise_seed: int) -> dict:
    """One episode from ``seed``'s start; the per-step state read back from the observation."""
    obs, first_success = rollout_states(actor, task, seed, noise_seed=noise_seed, obs_horizon=obs_horizon)
    if obs.shape[1] != STATE_DIM:
        raise ValueError(f"task {task.name}: state of size {obs.shape[1]}, expected Can's {STATE_DIM}")
    can, hand = obs[:, CAN], obs[:, EEF]
    lift = can[:, 2] - can[0, 2]
    hand_dist = np.linalg.norm(hand - can, axis=1)
    over_bin = (
        (BIN_X[0] < can[:, 0]) & (can[:, 0] < BIN_X[1]) & (BIN_Y[0] < can[:, 1]) & (can[:, 1] < BIN_Y[1])
    )
    lifted = lift > LIFT
    hand_xy = np.linalg.norm(hand[:, :2] - can[:, :2], axis=1)
    closest_xy = int(hand_xy.argmin())
    close_step, offset = first_close(obs)
    return {
        "seed": seed,
        "steps": len(obs) - 1,
        "first_success_step": first_success,
        "first_lift_step": int(lifted.argmax()) if lifted.any() else None,
        "max_lift": round(float(lift.max()), 3),
        "hand_dist_min": round(float(hand_dist.min()), 3),
        # a reach that ends beside the can and one that ends above it fail differently
        "hand_xy_dist_min": round(float(hand_xy[closest_xy]), 3),
        "hand_height_at_xy_min": round(float(hand[closest_xy, 2] - can[closest_xy, 2]), 3),
        # the hand pushed or toppled the can before any lift
        "can_moved_xy": round(float(np.linalg.norm(can[-1, :2] - can[0, :2])), 3),
        "can_start": [round(float(v), 3) for v in can[0]],
        # where the hand was, sideways from the can, when the fingers first closed: a miss that points
        # toward the start bin's centre is a grasp pulled toward the demonstrations' average start
        "close_step": close_step,
        "hand_offset_xy_at_close": offset,
        "held_at_end": bool(hand_dist[-1] < HOLD and lift[-1] > 0.01),
        "first_over_bin_step": int(over_bin.argmax()) if over_bin.any() else None,
        "can_end": [round(float(v), 3) for v in can[-1]],
    }


def phase(row: dict) -> str:
    """The one phase an episode ended in (see the module's docstring)."""
    if row["first_success_step"] is not None:
        return "success"
    if row["first_lift_step"] is None:
        return "no_lift"
    if row["first_over_bin_step"] is not None:
        return "over_bin_not_placed"
    if row["held_at_end"]:
        return "carried_not_over_bin"
    return "dropped"


def main(argv: list[str] | None = None) -> int:
    return diagnose(
        argv,
        description=__doc__.splitlines()[0],
        env_id="PickPlaceCan",
        play=play,
        phase=phase,
        constants={"lift": LIFT, "hold": HOLD, "bin_x": BIN_X, "bin_y": BIN_Y},
    )


if __name__ == "__main__":
    raise SystemExit(main())
