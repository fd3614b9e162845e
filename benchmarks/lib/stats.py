"""Figures over seeds and along validation curves: mean and spread, steps to a fraction of the best,
whether a curve was still rising (a convergence figure that is only a bound)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

__all__ = ["convergence_steps", "mean_and_spread", "steps_to_fraction_of_best", "still_rising"]


def mean_and_spread(values: Sequence[float]) -> dict[str, float]:
    """Mean, sample standard deviation, min and max over seeds."""
    n = len(values)
    if n == 0:
        return {"mean": math.nan, "std": math.nan, "min": math.nan, "max": math.nan, "n": 0}
    mean = sum(values) / n
    var = sum((v - mean) ** 2 for v in values) / (n - 1) if n > 1 else 0.0
    return {"mean": mean, "std": math.sqrt(var), "min": min(values), "max": max(values), "n": n}


def steps_to_fraction_of_best(curve: Sequence[tuple[int, float]], fraction: float = 0.9) -> int | None:
    """The first step at which the curve reaches ``fraction`` of its best value (None: empty or 0)."""
    if not curve:
        return None
    best = max(v for _, v in curve)
    if best <= 0:
        return None
    return next(step for step, v in curve if v >= fraction * best)


def still_rising(curve: Sequence[tuple[int, float]], fraction: float = 0.9) -> bool:
    """Whether the curve first came within ``fraction`` of its best at its last validation: it had not
    flattened within the budget, so its steps-to-``fraction`` is a lower bound, not a measurement."""
    if len(curve) < 2:
        return False
    return steps_to_fraction_of_best(curve, fraction) == curve[-1][0]


def convergence_steps(block: dict[str, Any]) -> list[tuple[int, bool]]:
    """Per seed of a success file's method block: (steps to 90 % of its best, still rising at the end).

    Read from the saved curves where the block has them (files from before ``still_rising`` existed
    included), else from its steps-to-90 % figures, which cannot say whether a curve was still rising."""
    curves = [[(int(s), float(v)) for s, v in c] for c in block.get("curves") or []]
    if curves:
        steps = [(steps_to_fraction_of_best(c), still_rising(c)) for c in curves]
    else:
        steps = [(s, False) for s in block.get("steps_to_90pct_of_best") or []]
    return [(s, rising) for s, rising in steps if s]
