"""Baseline: velocity-prediction flow matching (MSE, pi0-style Beta time, Euler sampling)."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import Tensor

from l1flow_rl.flow.time import interpolate
from l1flow_rl.flow.timesteps import TimestepDistribution, make_timesteps
from l1flow_rl.objectives.chunk_loss import ChunkLossBase
from l1flow_rl.utils.doc_examples import chunk_loss_example

__all__ = ["FlowMatchingLoss"]


@chunk_loss_example("VelocityEulerSampler(10)")
class FlowMatchingLoss(ChunkLossBase):
    """The network predicts the velocity ``x1 - x0`` along the straight path; loss ``|v_hat - (x1 - x0)|^2``.

    Args:
        actor_network: an :class:`~l1flow_rl.L1FlowActor` built with ``sampler=VelocityEulerSampler(10)``.
        timesteps: ``"beta"`` (default; Beta(1, 1.5) scaled by 0.999), ``"uniform"``, ``"mixed"``
            or a :class:`~l1flow_rl.flow.TimestepDistribution`.
    """

    loss_name = "loss_flow_matching"
    prediction = "velocity"
    sampler_hint = "L1FlowActor.for_state(..., sampler=VelocityEulerSampler(10))"
    diagnostic_keys = ("t_mean",)

    def __init__(
        self,
        actor_network: TensorDictModule,
        *,
        timesteps: str | TimestepDistribution = "beta",
        reduction: str = "mean",
        mask_padding: bool = False,
    ) -> None:
        super().__init__(actor_network, reduction=reduction, mask_padding=mask_padding)
        self.timesteps = make_timesteps(timesteps)

    def _elementwise_loss(
        self, cond: Tensor, x1: Tensor, valid: Tensor | None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        t = self.timesteps.sample(x1.shape[0], device=x1.device).to(x1.dtype)
        x0 = torch.randn_like(x1)
        v_hat = self.policy.denoise(interpolate(x0, x1, t), t, cond)
        return (v_hat - (x1 - x0)).square(), {"t_mean": t.mean()}
