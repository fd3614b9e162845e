"""Baseline: Diffusion Policy's DDPM epsilon-prediction objective."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import Tensor

from l1flow_rl.objectives.chunk_loss import ChunkLossBase
from l1flow_rl.utils.doc_examples import chunk_loss_example

__all__ = ["DiffusionLoss"]


@chunk_loss_example("DDPMSampler()")
class DiffusionLoss(ChunkLossBase):
    """Noise a chunk to a random DDPM step k (squaredcos_cap_v2) and regress the noise with MSE.

    The network sees the integer step k. Sample with ``DDPMSampler()`` (100 NFE) or
    ``DDIMSampler(k)``; both share the schedule this loss trains on.
    """

    loss_name = "loss_diffusion"
    prediction = "epsilon"
    sampler_hint = "L1FlowActor.for_state(..., sampler=DDPMSampler()) or sampler=DDIMSampler(16)"
    diagnostic_keys = ()

    def __init__(
        self, actor_network: TensorDictModule, *, reduction: str = "mean", mask_padding: bool = False
    ):
        super().__init__(actor_network, reduction=reduction, mask_padding=mask_padding)
        self.schedule = self.policy.sampler.schedule  # type: ignore[attr-defined]

    def _elementwise_loss(
        self, cond: Tensor, x1: Tensor, valid: Tensor | None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        steps = torch.randint(0, self.schedule.num_train_timesteps, (x1.shape[0],), device=x1.device)
        noise = torch.randn_like(x1)
        eps_hat = self.policy.denoise(self.schedule.add_noise(x1, noise, steps), steps.to(x1.dtype), cond)
        return (eps_hat - noise).square(), {}
