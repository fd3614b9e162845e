"""Mixed-quality demonstrations (``demos.quality=mixed``): expert episodes plus perturbed ones, each
labelled, as robomimic's multi-human (MH) sets mix operators of different skill.

A mixed set of ``num`` episodes starts from ``num`` expert demonstrations. Each episode is assigned a
kind (:data:`MIXED_SHARES`, shuffled by the seed); a perturbed kind's actions are changed by
:func:`perturb_actions` and played again from the same initial scene, so that its observations,
rewards and success are the simulator's. The label is the outcome: ``failed`` when the played
episode does not succeed, its kind otherwise (a ``drop`` that still succeeds is ``recovered``).

Labels (:data:`QUALITY_LABELS`):
    expert: the expert's episode, unchanged.
    noisy: a wobbling, hesitant operator: correlated noise on the arm's actions and 1-3 pauses.
    recovered: a grasp closed too early (a few cm above the object), opened again, then the
        expert's grasp.
    failed: an episode that does not succeed (by design, a ``drop``: the gripper opens during the
        carry; or a noisy / recovered episode that did not make it). Its rewards say so.
    shifted: a successful episode replayed with its approach moved to another scene's object
        (``demos.shifted_replays``, :mod:`l1flow_rl.experts.object_shift`); only successes are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from l1flow_rl.config.data import QUALITIES, QUALITY_LABELS

__all__ = [
    "MIXED_SHARES",
    "QUALITIES",
    "QUALITY_LABELS",
    "GripperLayout",
    "check_quality",
    "label_of",
    "mixed_kinds",
    "perturb_actions",
]

#: the planned share of each kind in a mixed set; ``drop`` episodes are meant to fail
MIXED_SHARES = {"expert": 0.4, "noisy": 0.25, "recovered": 0.2, "drop": 0.15}


def check_quality(quality: str, where: str = "demos.quality") -> None:
    if quality not in QUALITIES:
        raise ValueError(f"{where}={quality!r}: expected one of {list(QUALITIES)}")


def mixed_kinds(num: int, seed: int) -> list[str]:
    """The kind of each of ``num`` episodes: shares as :data:`MIXED_SHARES` (rounded), shuffled by
    ``seed``; the expert gets the remainder."""
    counts = {k: round(share * num) for k, share in MIXED_SHARES.items() if k != "expert"}
    kinds = [k for k, n in counts.items() for _ in range(n)][:num]
    kinds += ["expert"] * (num - len(kinds))
    np.random.default_rng([seed, 31]).shuffle(kinds)
    return kinds


def label_of(kind: str, success: bool) -> str:
    if not success:
        return "failed"
    return "recovered" if kind == "drop" else kind


@dataclass(frozen=True)
class GripperLayout:
    """How a task's actions drive the gripper and the arm's position.

    Args:
        control: ``absolute`` (position targets: a pause repeats the last action) or ``delta``
            (displacements: a pause is zero motion).
        open, closed: the last action dim's value for an open and a closed gripper.
        metres_per_unit: for delta control, the displacement one action unit commands (to express
            the false grasp's rise in action units); 1 for absolute control.
    """

    control: str
    open: float
    closed: float
    metres_per_unit: float = 1.0

    def is_closed(self, value: float) -> bool:
        return abs(value - self.closed) < abs(value - self.open)


def _first_close(actions: np.ndarray, grip: GripperLayout) -> int | None:
    closed = [i for i, a in enumerate(actions) if grip.is_closed(a[-1])]
    return closed[0] if closed else None


def _pause(action: np.ndarray, steps: int, grip: GripperLayout) -> np.ndarray:
    held = np.repeat(action[None], steps, 0)
    if grip.control == "delta":
        held[:, :-1] = 0.0  # no motion, the gripper as it was
    return held


def _noisy(actions: np.ndarray, rng: np.random.Generator, grip: GripperLayout) -> np.ndarray:
    out = actions.copy()
    # correlated (AR(1)) noise on the position dims: a wobble rather than white jitter
    sigma = rng.uniform(0.003, 0.008) / grip.metres_per_unit
    noise = np.zeros(3)
    for t in range(len(out)):
        noise = 0.8 * noise + rng.normal(0.0, sigma, 3)
        out[t, :3] += noise if grip.control == "absolute" else noise * 0.2  # deltas accumulate
    for _ in range(int(rng.integers(1, 4))):
        at = int(rng.integers(1, len(out)))
        out = np.concatenate([out[:at], _pause(out[at - 1], int(rng.integers(4, 13)), grip), out[at:]])
    return out


def _false_grasp(actions: np.ndarray, rng: np.random.Generator, grip: GripperLayout) -> np.ndarray:
    at = _first_close(actions, grip)
    if at is None or at == 0:
        raise ValueError("the episode never closes the gripper: no grasp to fumble")
    before = actions[at - 1]
    rise = rng.uniform(0.03, 0.06) / grip.metres_per_unit
    n = int(rng.integers(4, 8))
    up, down = np.repeat(before[None], n, 0), np.repeat(before[None], n, 0)
    if grip.control == "absolute":
        up[:, 2] += np.linspace(rise / n, rise, n)
        down[:, 2] += np.linspace(rise, 0.0, n + 1)[1:]
        top = up[-1]
    else:
        up[:, :-1] = 0.0
        down[:, :-1] = 0.0
        up[:, 2], down[:, 2] = rise / n, -rise / n
        top = up[-1].copy()
        top[:-1] = 0.0
    close = np.repeat(top[None], int(rng.integers(6, 11)), 0)
    close[:, -1] = grip.closed
    reopen = np.repeat(top[None], int(rng.integers(4, 9)), 0)
    reopen[:, -1] = grip.open
    return np.concatenate([actions[:at], up, close, reopen, down, actions[at:]])


def _drop(actions: np.ndarray, rng: np.random.Generator, grip: GripperLayout) -> np.ndarray:
    at = _first_close(actions, grip)
    if at is None:
        raise ValueError("the episode never closes the gripper: nothing to drop")
    out = actions.copy()
    start = min(len(out) - 1, at + int(rng.integers(12, 25)))  # once lifted, during the carry
    out[start:, -1] = grip.open
    return out


_PERTURB = {"noisy": _noisy, "recovered": _false_grasp, "drop": _drop}


def perturb_actions(
    actions: np.ndarray, kind: str, rng: np.random.Generator, grip: GripperLayout
) -> np.ndarray:
    """An expert episode's actions [T, A] changed as ``kind`` says (see the module docstring); the
    result may be longer (pauses, a false grasp). ``expert`` returns them unchanged."""
    if kind == "expert":
        return np.asarray(actions).copy()
    try:
        perturb = _PERTURB[kind]
    except KeyError:
        raise ValueError(f"unknown perturbation {kind!r}; known: {['expert', *_PERTURB]}") from None
    return perturb(np.asarray(actions, dtype=np.float64), rng, grip)
