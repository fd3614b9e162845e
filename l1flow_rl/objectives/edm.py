"""Baseline: Diffusion Policy on EDM's noise schedule (Karras et al. 2022): preconditioned denoiser,
log-normal noise levels, EDM's loss weight, squared error (NVlabs/edm, as OneDP's EDM teacher).

Departure from Consistency Policy's released EDM teacher, on purpose: CP shifts c_skip/c_out by its
sigma_min 0.02 (the boundary form) and trains with a pseudo-Huber distance; this is Karras' form.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import Tensor

from l1flow_rl.objectives.chunk_loss import ChunkLossBase
from l1flow_rl.utils.doc_examples import chunk_loss_example

__all__ = ["EDMLoss"]


@chunk_loss_example("EDMHeunSampler(18)")
class EDMLoss(ChunkLossBase):
    """Noise a chunk to ``sigma = exp(p_mean + p_std * N(0, 1))`` (EDM's log-normal levels, -1.2 and
    1.2), denoise it with the preconditioned network D(x, sigma) = c_skip x + c_out F(c_in x, c_noise)
    and weight the squared error by EDM's ``(sigma^2 + sd^2) / (sigma sd)^2``.

    The preconditioning (sigma_data) is the actor's sampler's (:class:`~l1flow_rl.flow.EDMHeunSampler`,
    :mod:`l1flow_rl.flow.karras`), so training and sampling cannot disagree on it; ``c_noise = ln(sigma)/4``
    enters the network where every method's time does (scaled by ``network.timestep_scale``).

    Returns ``"loss_edm"`` and the detached diagnostics ``"sigma_median"`` and ``"x_error_l1"`` (mean
    |D - x0| in normalised units).
    """

    loss_name = "loss_edm"
    prediction = "karras"
    sampler_hint = "L1FlowActor.for_state(..., sampler=EDMHeunSampler(18))"
    diagnostic_keys = ("sigma_median", "x_error_l1")

    def __init__(
        self,
        actor_network: TensorDictModule,
        *,
        p_mean: float = -1.2,
        p_std: float = 1.2,
        reduction: str = "mean",
        mask_padding: bool = False,
    ) -> None:
        if not p_std > 0:
            raise ValueError(f"p_std must be positive, got {p_std}")
        super().__init__(actor_network, reduction=reduction, mask_padding=mask_padding)
        self.p_mean, self.p_std = float(p_mean), float(p_std)
        self.precond = self.policy.sampler.preconditioning  # type: ignore[attr-defined]

    def _elementwise_loss(
        self, cond: Tensor, x1: Tensor, valid: Tensor | None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        sigma = (torch.randn(x1.shape[0], device=x1.device, dtype=x1.dtype) * self.p_std + self.p_mean).exp()
        noisy = x1 + sigma.reshape(-1, 1, 1) * torch.randn_like(x1)
        denoised = self.precond.denoise(lambda x, c: self.policy.denoise(x, c, cond), noisy, sigma)
        err = self.precond.loss_weight(sigma).reshape(-1, 1, 1) * (denoised - x1).square()
        return err, {
            "sigma_median": sigma.median(),
            "x_error_l1": self._valid_mean((denoised - x1).abs(), valid),
        }
