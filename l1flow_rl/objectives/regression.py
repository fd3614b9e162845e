"""Baseline: plain L1 regression of the chunk on the same network, with no noise and no timestep."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import Tensor

from l1flow_rl.flow.objectives import LossType, check_loss_type, pointwise_error
from l1flow_rl.objectives.chunk_loss import ChunkLossBase
from l1flow_rl.utils.doc_examples import chunk_loss_example

__all__ = ["RegressionLoss"]


@chunk_loss_example("DirectSampler()")
class RegressionLoss(ChunkLossBase):
    """``|f(0, obs) - x1|``: the UNet gets a zero chunk and no timestep (``DirectSampler``).

    On multi-modal demonstrations this collapses to the conditional median/mean, which is the
    contrast L1 Flow is measured against.
    """

    loss_name = "loss_regression"
    prediction = "direct"
    sampler_hint = "L1FlowActor.for_state(..., sampler=DirectSampler())"
    diagnostic_keys = ()

    def __init__(
        self,
        actor_network: TensorDictModule,
        *,
        loss_type: LossType = "l1",
        reduction: str = "mean",
        mask_padding: bool = False,
    ) -> None:
        loss_type = check_loss_type(loss_type)  # before the network is taken over
        super().__init__(actor_network, reduction=reduction, mask_padding=mask_padding)
        self.loss_type = loss_type

    def _elementwise_loss(
        self, cond: Tensor, x1: Tensor, valid: Tensor | None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        diff = self.policy.denoise(torch.zeros_like(x1), None, cond) - x1
        return pointwise_error(diff, self.loss_type), {}
