"""Object-centric shifts of an absolute-control episode (MimicGen's idea, in the table's plane): the
approach and the grasp are relative to the object, the place is relative to the fixed goal.

An episode recorded with the object at ``p`` (yaw ``a``) is replayed with the object at ``p + d``
(yaw ``a + turn``) by moving every absolute pose target with the object: ``w_t = 1`` up to ``hold``
steps after the final grasp closes (the approach, the grasp and the start of the lift follow the
object), then ``w_t`` fades linearly to 0 at the release (the carry bends back to the recorded
place), and stays 0 after. At weight ``w`` a target's position is turned by ``w * turn`` about the
vertical through ``p`` and moved by ``w * d``, and its orientation turned by ``w * turn`` about the
vertical. The played episode's observations and success are the simulator's (see
:mod:`l1flow_rl.experts.robosuite.shifted`); nothing here assumes that the shifted episode succeeds.

A round object (a can) grasps alike at any yaw and needs the translation only (``turn=0``); a nut
or a tool needs the turn too.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from l1flow_rl.experts.quality import GripperLayout

__all__ = ["final_grasp", "shift_actions", "shift_weights"]

#: an absolute OSC_POSE action: position (3), axis-angle orientation (3), ..., gripper (last)
_ROTATION = slice(3, 6)


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


def _same_side(rotvec: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Each axis-angle row of ``rotvec`` written on the side (``r`` or ``r - 2 pi r / |r|``, the same
    rotation) nearer to ``reference``'s row: a top-down gripper is a rotation by ~pi, where scipy may
    pick either side, and a jump of ~2 pi between steps is not what the recorded actions did."""
    angle = np.linalg.norm(rotvec, axis=1, keepdims=True)
    other = rotvec - 2 * np.pi * rotvec / np.maximum(angle, 1e-12)
    nearer = np.linalg.norm(other - reference, axis=1) < np.linalg.norm(rotvec - reference, axis=1)
    return np.where(nearer[:, None] & (angle > 1e-6), other, rotvec)


def shift_actions(
    actions: np.ndarray,
    offset: np.ndarray,
    grip: GripperLayout,
    hold: int = 10,
    *,
    turn: float = 0.0,
    pivot: np.ndarray | None = None,
) -> np.ndarray:
    """``actions`` [T, A] (absolute world-frame position targets in dims 0-2, axis-angle orientation
    targets in dims 3-5) moved with the object (see the module docstring): ``offset`` has 2 (x, y) or
    3 entries; ``turn`` (radians about the vertical) needs ``pivot``, the object's recorded position.
    With ``turn=0`` only the position dims change. Other dims are unchanged."""
    if grip.control != "absolute":
        raise ValueError(
            f"an object shift moves absolute position targets; this task's control is {grip.control!r} "
            "(a delta action would need the shift's increments instead)"
        )
    actions = np.asarray(actions, dtype=np.float64)
    offset = np.asarray(offset, dtype=np.float64)
    if offset.shape not in ((2,), (3,)):
        raise ValueError(f"offset has shape {offset.shape}: expected (2,) for x, y or (3,) for x, y, z")
    weights = shift_weights(actions, grip, hold)
    out = actions.copy()
    if turn:
        if pivot is None or np.shape(pivot) not in ((2,), (3,)):
            raise ValueError(f"turn={turn}: expected the object's recorded x, y as pivot, got {pivot!r}")
        if actions.shape[1] < 7:
            raise ValueError(
                f"turn={turn}: expected OSC_POSE actions (position, axis-angle, gripper), "
                f"got {actions.shape[1]} dims"
            )
        moving = weights > 0  # the steps after the release stay exactly as recorded
        angles = weights[moving] * turn
        cos, sin = np.cos(angles), np.sin(angles)
        dx, dy = (actions[moving, :2] - np.asarray(pivot, dtype=np.float64)[:2]).T
        out[moving, 0] = pivot[0] + cos * dx - sin * dy
        out[moving, 1] = pivot[1] + sin * dx + cos * dy
        rotvec = actions[moving, _ROTATION]
        turned = (Rotation.from_euler("z", angles[:, None]) * Rotation.from_rotvec(rotvec)).as_rotvec()
        out[moving, _ROTATION] = _same_side(turned, rotvec)
    out[:, : len(offset)] += weights[:, None] * offset
    return out
