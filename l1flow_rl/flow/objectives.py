"""Sample-prediction objectives: L1 or MSE, measured in x-space or in v-space."""

from __future__ import annotations

from typing import Literal

from torch import Tensor

from l1flow_rl.flow.time import broadcast_time

__all__ = ["LossSpace", "LossType", "check_loss_type", "pointwise_error", "sample_prediction_error"]

LossType = Literal["l1", "mse"]
LossSpace = Literal["x", "v"]

# (1 - t) floor for v-space errors, as in the official L1 Flow code: keeps the weight below 20.
V_SPACE_MIN_REMAINING = 0.05


def sample_prediction_error(
    x1_hat: Tensor,
    x1: Tensor,
    t: Tensor,
    loss_type: LossType = "l1",
    space: LossSpace = "x",
    min_remaining: float = V_SPACE_MIN_REMAINING,
) -> Tensor:
    """Element-wise error of a sample prediction ``x1_hat`` of ``x1`` at flow time ``t`` ([B]).

    In v-space both the predicted and the true velocity share ``x_t``, so their difference is
    ``(x1_hat - x1) / (1 - t)``: the v-space loss is the x-space error weighted by 1/(1 - t)
    (squared for MSE), with ``1 - t`` clamped at ``min_remaining``.
    """
    diff = x1_hat - x1
    if space == "v":
        diff = diff / (1.0 - broadcast_time(t, diff)).clamp_min(min_remaining)
    elif space != "x":
        raise ValueError(f"loss space must be 'x' or 'v', got {space!r}")
    return pointwise_error(diff, loss_type)


def check_loss_type(loss_type: str) -> LossType:
    """``loss_type`` itself when it is ``"l1"`` or ``"mse"``; else a ValueError naming it."""
    if loss_type not in ("l1", "mse"):
        raise ValueError(f"loss_type must be 'l1' or 'mse', got {loss_type!r}")
    return loss_type  # type: ignore[return-value]


def pointwise_error(diff: Tensor, loss_type: LossType) -> Tensor:
    """``|diff|`` (``"l1"``) or ``diff ** 2`` (``"mse"``), element-wise."""
    return diff.abs() if check_loss_type(loss_type) == "l1" else diff.square()
