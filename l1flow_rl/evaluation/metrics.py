"""Per-episode metrics to summary figures with 95 % confidence intervals.

A rate (a yes/no per episode: success) gets the Wilson score interval, which stays inside [0, 1]
and is sensible at 0/n and n/n, where the normal approximation collapses to a point. A mean
(return, length, a score) gets Student's t interval, mean ± t(0.975, n-1) · s / sqrt(n).
Hand-written: the formulas are two lines each, and SciPy's ``binomtest`` interval is not Wilson's
by default.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

__all__ = ["MEAN", "RATE", "mean_interval", "summarize_metrics", "wilson_interval"]

RATE, MEAN = "rate", "mean"
_Z95 = 1.959963984540054  # the standard normal's 0.975 quantile


def wilson_interval(successes: int, n: int) -> tuple[float, float]:
    """95 % Wilson score interval of a success rate ``successes / n``.

    Example:
        >>> lo, hi = wilson_interval(48, 50)
        >>> round(lo, 4), round(hi, 4)
        (0.8654, 0.989)
    """
    if n < 1:
        raise ValueError(f"a rate needs at least one episode, got n={n}")
    if not 0 <= successes <= n:
        raise ValueError(f"successes must lie in [0, {n}], got {successes}")
    p, z2 = successes / n, _Z95**2
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = _Z95 * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    # at 0 (or n) successes the bound is exactly 0 (or 1); rounding would leave it 1e-17 off the point
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    return low, 1.0 if successes == n else min(1.0, centre + half)


def mean_interval(values: Sequence[float]) -> tuple[float, float] | tuple[None, None]:
    """95 % Student-t interval of the mean; ``(None, None)`` for fewer than 2 values."""
    x = np.asarray(values, dtype=np.float64)
    if x.size < 2:
        return None, None
    from scipy.stats import t as student_t  # every simulator extra installs SciPy

    half = float(student_t.ppf(0.975, x.size - 1)) * float(x.std(ddof=1)) / math.sqrt(x.size)
    return float(x.mean() - half), float(x.mean() + half)


def summarize_metrics(per_episode: Sequence[Mapping[str, Any]], kinds: Mapping[str, str]) -> dict[str, Any]:
    """``{name: {"mean", "ci95_low", "ci95_high", "interval", "n"}}`` for each metric in ``kinds``
    (name -> :data:`RATE` or :data:`MEAN`), read from every episode's record; an episode that
    reported no value for a metric (None: it ended before its first step) is left out of it."""
    out: dict[str, Any] = {}
    for name, kind in kinds.items():
        values = [r[name] for r in per_episode if r.get(name) is not None]
        n = len(values)
        if n == 0:
            out[name] = {"mean": None, "ci95_low": None, "ci95_high": None, "interval": None, "n": 0}
            continue
        if kind == RATE:
            hits = sum(bool(v) for v in values)
            low, high = wilson_interval(hits, n)
            method, mean = "wilson", hits / n
        elif kind == MEAN:
            low, high = mean_interval(values)
            method, mean = "t", float(np.mean(values))
        else:
            raise ValueError(f"metric {name!r}: kind must be {RATE!r} or {MEAN!r}, got {kind!r}")
        out[name] = {"mean": mean, "ci95_low": low, "ci95_high": high, "interval": method, "n": n}
    return out
