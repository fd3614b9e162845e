"""Exponential moving average of a policy with Diffusion Policy's warm-up schedule.

Built on ``torch.optim.swa_utils.AveragedModel`` (its copy of the model, its ``n_averaged`` counter
and state_dict layout); the decay schedule and the update are ours. ``AveragedModel``'s own update
passes the counter to the averaging function as a tensor on the parameters' device, so a decay that
depends on the count would read it back once per parameter: on a GPU, a host synchronisation each.
Here the counter stays on the CPU, the decay is a Python float, and all parameters move with one
``torch._foreach_lerp_``.
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

    The first update copies the weights; the n-th later one blends them with decay
    ``dp_ema_decay(n - 1, power, inv_gamma, max_decay)`` (Diffusion Policy's ``EMAModel``, whose
    first two updates are copies), as ``ema <- lerp(ema, live, 1 - decay)``.

    Buffers (the normalisers, including their integer mode) are not averaged: the average of the
    same integer can round down, and a normaliser fitted after the copy was made must still reach
    the average. They are copied on every update.

    ``n_averaged`` is kept on the CPU even when the module moves to a GPU: the host reads it every
    update to compute the decay, and a read of a GPU tensor would wait for the device.
    """

    def __init__(
        self, model: nn.Module, power: float = 0.75, inv_gamma: float = 1.0, max_decay: float = 0.9999
    ) -> None:
        super().__init__(model, use_buffers=False)
        self.power, self.inv_gamma, self.max_decay = power, inv_gamma, max_decay

    def _apply(self, fn, recurse: bool = True):
        counter = self.n_averaged
        super()._apply(fn, recurse)
        self.n_averaged = counter  # the step counter stays a CPU tensor (see the class docstring)
        return self

    def decay(self) -> float:
        """The decay the next update blends with (0: it copies)."""
        n = int(self.n_averaged)  # a CPU tensor: no device synchronisation
        return 0.0 if n == 0 else dp_ema_decay(n - 1, self.power, self.inv_gamma, self.max_decay)

    @torch.no_grad()
    def update_parameters(self, model: nn.Module) -> None:
        mine = [p.detach() for p in self.module.parameters()]
        theirs = [p.detach() for p in model.parameters()]
        if len(mine) != len(theirs):
            raise ValueError(
                f"the EMA holds {len(mine)} parameters but the model passed has {len(theirs)}; "
                "update the EMA with the model it was made from"
            )
        decay = self.decay()
        if decay == 0.0:
            torch._foreach_copy_(mine, theirs)
        else:
            torch._foreach_lerp_(mine, theirs, 1.0 - decay)
        own_buffers = [b.detach() for b in self.module.buffers()]
        if own_buffers:
            torch._foreach_copy_(own_buffers, [b.detach() for b in model.buffers()])
        self.n_averaged += 1


def make_ema(
    model: nn.Module, power: float = 0.75, inv_gamma: float = 1.0, max_decay: float = 0.9999
) -> DPEma:
    """An averaged copy of ``model``; call ``ema.update_parameters(model)`` after each optimiser step.

    The first call copies the weights; the n-th later call blends with
    ``dp_ema_decay(n - 1, power)``, the schedule of Diffusion Policy's ``EMAModel`` (whose first
    two updates are copies). Buffers (the normalisers) are copied, not averaged. The averaged
    policy is ``ema.module``; it lives on ``model``'s device.

    Examples:
        >>> import torch
        >>> net = torch.nn.Linear(2, 1)
        >>> ema = make_ema(net)
        >>> ema.update_parameters(net)
        >>> torch.equal(ema.module.weight, net.weight)
        True
    """
    return DPEma(model, power=power, inv_gamma=inv_gamma, max_decay=max_decay)
