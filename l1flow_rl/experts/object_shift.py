"""Object-centric shifts of an absolute-control episode (MimicGen's idea, translation only): the
approach and the grasp are relative to the object, the place is relative to the fixed goal.

An episode recorded with the object at ``p`` is replayed with the object at ``p + d`` by adding
``w_t * d`` to every absolute position target: ``w_t = 1`` up to ``hold`` steps after the final
grasp closes (the approach, the grasp and the start of the lift follow the object), then ``w_t``
fades linearly to 0 at the release (the carry bends back to the recorded place), and stays 0 after.
The played episode's observations and success are the simulator's (see
:mod:`l1flow_rl.experts.robosuite.shifted`); nothing here assumes that the shifted episode succeeds.

Only translation is shifted: an object whose grasp depends on its yaw (a nut, a tool) needs the
rotation transformed too, which this does not do.
"""

from __future__ import annotations

import numpy as np

from l1flow_rl.experts.quality import GripperLayout

__all__ = ["final_grasp", "shift_actions", "shift_weights"]


def final_grasp(actions: np.ndarray, grip: GripperLayout) -> tuple[int, int]:
    """(onset, release) of the episode's last closed run of the gripper: the first closed step and
    the first open step after it (``len(actions)`` when it never opens again). An earlier closed
    run (a false grasp that re-opens) is part of the approach."""
    closed = np.array([grip.is_closed(a) for a in np.asarray(actions)[:, -1]])
    if not closed.any():
        raise ValueError("the episode never closes the gripper: no grasp to shift the approach to")
    rises = np.flatnonzero(closed[1:] & ~closed[:-1]) + 1
    onset = int(rises[-1]) if len(rises) else 0
    opens = np.flatnonzero(~closed[onset:])
    release = onset + int(opens[0]) if len(opens) else len(actions)
    return onset, release


def shift_weights(actions: np.ndarray, grip: GripperLayout, hold: int = 10) -> np.ndarray:
    """``w_t`` [T] (see the module docstring): 1 until ``hold`` steps after the final grasp's onset,
    linear to 0 at its release, 0 after."""
    if hold < 0:
        raise ValueError(f"hold={hold}: expected >= 0 steps")
    onset, release = final_grasp(actions, grip)
    weights = np.ones(len(actions))
    fade_from = min(onset + hold, release)
    weights[fade_from:release] = np.linspace(1.0, 0.0, release - fade_from + 1)[:-1]
    weights[release:] = 0.0
    return weights


def shift_actions(actions: np.ndarray, offset: np.ndarray, grip: GripperLayout, hold: int = 10) -> np.ndarray:
    """``actions`` [T, A] (absolute position targets in dims 0-2) with ``w_t * offset`` added to
    the position dims; ``offset`` has 2 (x, y) or 3 entries. Other dims are unchanged."""
    if grip.control != "absolute":
        raise ValueError(
            f"an object shift moves absolute position targets; this task's control is {grip.control!r} "
            "(a delta action would need the shift's increments instead)"
        )
    actions = np.asarray(actions, dtype=np.float64)
    offset = np.asarray(offset, dtype=np.float64)
    if offset.shape not in ((2,), (3,)):
        raise ValueError(f"offset has shape {offset.shape}: expected (2,) for x, y or (3,) for x, y, z")
    out = actions.copy()
    out[:, : len(offset)] += shift_weights(actions, grip, hold)[:, None] * offset
    return out
