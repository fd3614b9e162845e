"""Exponential moving average of a policy with Diffusion Policy's warm-up schedule.

Built on ``torch.optim.swa_utils.AveragedModel``; only the decay schedule and the buffer copy are ours.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.optim.swa_utils import AveragedModel

__all__ = ["DPEma", "dp_ema_decay", "make_ema"]


def dp_ema_decay(
    step: int | Tensor, power: float = 0.75, inv_gamma: float = 1.0, max_decay: float = 0.9999
) -> float:
    """Decay after ``step`` previous updates: ``1 - (1 + step / inv_gamma) ** -power``, in [0, max_decay].

    Step 0 gives decay 0 (copy the weights); the decay then rises towards ``max_decay``.

    Examples:
        >>> dp_ema_decay(0), round(dp_ema_decay(1), 4), dp_ema_decay(10**9)
        (0.0, 0.4054, 0.9999)
    """
    step = float(step)
    if step <= 0:
        return 0.0
    return min(max(1.0 - (1.0 + step / inv_gamma) ** -power, 0.0), max_decay)


class DPEma(AveragedModel):
    """``AveragedModel`` whose parameters follow :func:`dp_ema_decay` and whose buffers are copied.

    Buffers (the normalisers, including their integer mode) must not be averaged: the average of
    the same integer can round down, and a normaliser fitted after the copy was made must still
    reach the average. ``AveragedModel(use_buffers=False)`` leaves them untouched, so they are
    copied after every update.
    """

    def update_parameters(self, model: nn.Module) -> None:
        super().update_parameters(model)
        with torch.no_grad():
            for mine, theirs in zip(self.module.buffers(), model.buffers(), strict=True):
                mine.copy_(theirs)


def make_ema(
    model: nn.Module, power: float = 0.75, inv_gamma: float = 1.0, max_decay: float = 0.9999
) -> DPEma:
    """An averaged copy of ``model``; call ``ema.update_parameters(model)`` after each optimiser step.

    The first call copies the weights; the n-th later call blends with
    ``dp_ema_decay(n - 1, power)``, the schedule of Diffusion Policy's ``EMAModel`` (whose first
    two updates are copies). Buffers (the normalisers) are copied, not averaged. The averaged
    policy is ``ema.module``.

    Examples:
        >>> import torch
        >>> net = torch.nn.Linear(2, 1)
        >>> ema = make_ema(net)
        >>> ema.update_parameters(net)
        >>> torch.equal(ema.module.weight, net.weight)
        True
    """

    @torch.no_grad()
    def avg_fn(averaged: Tensor, current: Tensor, num_averaged: Tensor) -> Tensor:
        decay = dp_ema_decay(int(num_averaged) - 1, power, inv_gamma, max_decay)
        return averaged * decay + current * (1.0 - decay)

    return DPEma(model, avg_fn=avg_fn, use_buffers=False)
