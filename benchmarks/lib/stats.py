"""Figures over seeds and along validation curves: mean and spread, steps to a fraction of the best,
whether a curve was still rising (a convergence figure that is only a bound)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

__all__ = [
    "convergence_steps",
    "mean_and_spread",
    "runs_aggregate",
    "steps_to_fraction_of_best",
    "still_rising",
]


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


def runs_aggregate(per_seed: dict[int, dict]) -> dict:
    """A fine-tuning arm's runs (seed -> its record in a ``finetune_online_*.json``) over seeds: the test
    figure, and validation success at each env step that every seed reached."""
    tests = [
        r["test"]["success_once"] for r in per_seed.values() if r["test"].get("success_once") is not None
    ]
    curves = [{v["env_steps"]: v["success_once"] for v in r["validation"]} for r in per_seed.values()]
    common = sorted(set.intersection(*(set(c) for c in curves))) if curves else []
    return {
        "seeds": sorted(per_seed),
        "test_mean": sum(tests) / len(tests) if tests else None,
        "test_min": min(tests) if tests else None,
        "test_max": max(tests) if tests else None,
        "curve": [
            {
                "env_steps": x,
                "mean": sum(c[x] for c in curves) / len(curves),
                "min": min(c[x] for c in curves),
                "max": max(c[x] for c in curves),
            }
            for x in common
        ],
    }
