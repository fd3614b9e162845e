"""The time convention every flow in this library shares.

t = 0 is pure noise and t = 1 is data: ``x_t = (1 - t) * x0 + t * x1``. A sample-prediction
network f(x_t, t) estimates x1; its implied velocity is ``(f - x_t) / (1 - t)``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from l1flow_rl.utils.value_checks import value_checks_enabled

__all__ = ["broadcast_time", "check_time", "interpolate", "velocity_from_sample"]


def check_time(t: Tensor, name: str = "t") -> None:
    """Raise if any flow time lies outside [0, 1] or is not finite."""
    if not torch.isfinite(t).all():
        raise ValueError(f"flow time {name!r} contains NaN or Inf")
    lo, hi = float(t.min()), float(t.max())
    if lo < 0.0 or hi > 1.0:
        raise ValueError(
            f"flow time {name!r} must lie in [0, 1] (t=0 is noise, t=1 is data); got [{lo}, {hi}]"
        )


def broadcast_time(t: Tensor, like: Tensor, name: str = "t") -> Tensor:
    """Reshape a per-sample time ``[B]`` (or a scalar ``[]``) to broadcast against ``like`` ``[B, ...]``."""
    if t.dim() == 0:
        return t
    if like.dim() == 0 or tuple(t.shape) != (like.shape[0],):
        batch = like.shape[0] if like.dim() else "B"
        raise ValueError(f"flow time {name!r} must have shape [] or [{batch}], got {tuple(t.shape)}")
    return t.reshape(t.shape[0], *([1] * (like.dim() - 1)))


def interpolate(x0: Tensor, x1: Tensor, t: Tensor) -> Tensor:
    """The straight path ``x_t = (1 - t) x0 + t x1`` (t has shape [] or [B]).

    Examples:
        >>> interpolate(torch.zeros(2, 3), torch.ones(2, 3), torch.tensor([0.25, 1.0]))[:, 0]
        tensor([0.2500, 1.0000])
    """
    if x0.shape != x1.shape:
        raise ValueError(f"noise 'x0' must have the shape of 'x1' {tuple(x1.shape)}, got {tuple(x0.shape)}")
    if value_checks_enabled():  # off in the training loop, whose loss draws t itself
        check_time(t)
    tt = broadcast_time(t, x1)
    return (1.0 - tt) * x0 + tt * x1


def velocity_from_sample(x1_hat: Tensor, x_t: Tensor, t: Tensor, min_remaining: float = 0.0) -> Tensor:
    """Velocity implied by a sample prediction: ``(x1_hat - x_t) / (1 - t)``.

    ``min_remaining`` clamps ``1 - t`` from below; the samplers never evaluate at t = 1.
    """
    remaining = (1.0 - broadcast_time(t, x_t)).clamp_min(min_remaining)
    return (x1_hat - x_t) / remaining
