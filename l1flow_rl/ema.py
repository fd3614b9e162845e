"""Exponential moving average of a policy with Diffusion Policy's warm-up schedule.

Built on ``torch.optim.swa_utils.AveragedModel``; only the decay schedule is ours.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.optim.swa_utils import AveragedModel

__all__ = ["dp_ema_decay", "make_ema"]


def dp_ema_decay(step: int | Tensor, power: float = 0.75, inv_gamma: float = 1.0, max_decay: float = 0.9999) -> float:
    """Decay after ``step`` previous updates: ``1 - (1 + step / inv_gamma) ** -power``, in [0, max_decay].

    Step 0 gives decay 0 (copy the weights); the decay then rises towards ``max_decay``.
    """
    step = float(step)
    if step <= 0:
        return 0.0
    return min(max(1.0 - (1.0 + step / inv_gamma) ** -power, 0.0), max_decay)


def make_ema(model: nn.Module, power: float = 0.75, inv_gamma: float = 1.0, max_decay: float = 0.9999) -> AveragedModel:
    """An ``AveragedModel`` copy of ``model``; call ``ema.update_parameters(model)`` after each optimiser step.

    The first call copies the weights; the n-th later call blends with
    ``dp_ema_decay(n - 1, power)`` as Diffusion Policy's ``EMAModel`` does. Buffers (the
    normalisers) are copied, not averaged. The averaged policy is ``ema.module``.
    """

    @torch.no_grad()
    def avg_fn(averaged: Tensor, current: Tensor, num_averaged: Tensor) -> Tensor:
        decay = dp_ema_decay(int(num_averaged) - 1, power, inv_gamma, max_decay)
        return averaged * decay + current * (1.0 - decay)

    return AveragedModel(model, avg_fn=avg_fn, use_buffers=False)
