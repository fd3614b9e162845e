"""Consistency Policy (Prasad et al. 2024): consistency distillation of an EDM teacher."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import Tensor

from l1flow_rl.flow.karras import heun_step, ict_delta, pseudo_huber
from l1flow_rl.objectives.distillation import DistillationLossBase
from l1flow_rl.utils.doc_examples import distillation_example

__all__ = ["ConsistencyLoss"]

#: Consistency Policy's denoising term draws half its levels from the first 70 % of the rho schedule
#: (counted from sigma_max) and half from EDM's log-normal
_DSM_SCHEDULE_SPAN = 0.7


@distillation_example("EDMHeunSampler(18)", "ConsistencySampler(3)", 3)
class ConsistencyLoss(DistillationLossBase):
    """The student f(x, sigma) (boundary-conditioned Karras preconditioning: f(x, sigma_min) = x) learns
    to map every point of the teacher's probability-flow ODE to the same clean chunk.

    Each batch, on Consistency Policy's discretisation (``bins`` levels of the rho schedule, 80 from
    sigma_max 80 to sigma_min 0.02, the student sampler's):

    - consistency term: bin i uniform, ``x_t = x0 + sigma_i n``; one Heun step of the frozen EDM teacher
      takes it to ``x_u`` at ``sigma_{i+1}``; the loss is the pseudo-Huber distance (iCT's delta,
      ``0.00054 sqrt(H A)``) between ``f(x_t, sigma_i)`` and the target network's ``f(x_u, sigma_{i+1})``;
    - denoising term (weight ``dsm_weight``, 1 as in CP): ``f(x0 + sigma n, sigma)`` against ``x0`` with
      EDM's loss weight, sigma drawn half from the first 70 % of the schedule and half log-normal
      (-1.2, 1.2), clipped to [sigma_min, sigma_max].

    The target network is an exponential moving average of the student, updated at the start of each
    call with ``target_decay`` (CP's released recipe: 0, the student itself without gradient). The
    student starts from the teacher's weights. The jump always ends at sigma_min (the consistency-model
    case of CP's trajectory objective, its ``ctm_to_cm`` setting): the shared network takes one time
    input, so a stop time cannot be given to it.

    Args:
        actor_network: the student, an :class:`~l1flow_rl.L1FlowActor` with a
            :class:`~l1flow_rl.flow.ConsistencySampler`.
        teacher: the frozen teacher, an actor with an :class:`~l1flow_rl.flow.EDMHeunSampler`.

    Returns ``"loss_consistency"`` and the detached diagnostics ``"consistency_term"`` and
    ``"denoising_term"`` (their batch means).
    """

    loss_name = "loss_consistency"
    prediction = "consistency"
    sampler_hint = "L1FlowActor.for_state(..., sampler=ConsistencySampler(1))"
    diagnostic_keys = ("consistency_term", "denoising_term")
    teacher_predictions = ("karras",)

    def __init__(
        self,
        actor_network: TensorDictModule,
        *,
        teacher: TensorDictModule,
        target_decay: float = 0.0,
        dsm_weight: float = 1.0,
        huber_delta: float | None = None,
        init_from_teacher: bool = True,
        reduction: str = "mean",
        mask_padding: bool = False,
    ) -> None:
        if not 0.0 <= target_decay < 1.0:
            raise ValueError(f"target_decay must lie in [0, 1), got {target_decay}")
        if dsm_weight < 0:
            raise ValueError(f"dsm_weight must be >= 0, got {dsm_weight}")
        if huber_delta is not None and not huber_delta > 0:
            raise ValueError(f"huber_delta must be positive (or None for iCT's), got {huber_delta}")
        super().__init__(
            actor_network,
            teacher=teacher,
            init_from_teacher=init_from_teacher,
            reduction=reduction,
            mask_padding=mask_padding,
        )
        self.target_decay, self.dsm_weight = float(target_decay), float(dsm_weight)
        policy = self.policy
        self.huber_delta = huber_delta or ict_delta(policy.pred_horizon * policy.action_dim)
        self.sampler = policy.sampler
        # The target network's parameters: a detached copy, moved towards the student's each call.
        self.__dict__["_target"] = self.actor_network_params.data.clone()

    # -- the target network ------------------------------------------------------------------
    def _target_leaves(self) -> list[tuple[Tensor, Tensor]]:
        live = self.actor_network_params.data
        return list(zip(self._target.values(True, True), live.values(True, True)))

    @torch.no_grad()
    def update_target(self) -> None:
        """target <- decay * target + (1 - decay) * student (floating leaves; others copied)."""
        for target, live in self._target_leaves():
            if target.is_floating_point() and self.target_decay > 0:
                target.lerp_(live, 1.0 - self.target_decay)
            else:
                target.copy_(live)

    def training_state(self) -> dict[str, Tensor]:
        return {f"target.{k}": v for k, v in self._target.flatten_keys(".").items()}

    def load_training_state(self, state: dict[str, Tensor]) -> None:
        flat = self._target.flatten_keys(".")
        for key, value in flat.items():
            value.copy_(state[f"target.{key}"])

    # -- the loss -----------------------------------------------------------------------------
    def _consistency(self, cond: Tensor, x: Tensor, sigma: Tensor) -> Tensor:
        return self.sampler.preconditioning.denoise(
            lambda xin, c: self.policy.denoise(xin, c, cond), x, sigma
        )

    def _distill_loss(
        self, obs: TensorDictBase, cond: Tensor, teacher_cond: Tensor, x1: Tensor, valid: Tensor | None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        self.update_target()
        n, device, sampler = x1.shape[0], x1.device, self.sampler
        levels = sampler.bin_sigmas(device=device).to(x1.dtype)
        i = torch.randint(0, sampler.bins - 1, (n,), device=device)
        sigma_t, sigma_u = levels[i], levels[i + 1]
        x_t = x1 + sigma_t.reshape(-1, 1, 1) * torch.randn_like(x1)
        with torch.no_grad():
            view, teacher = self.teacher_view, self.teacher
            x_u = heun_step(lambda x, s: view.clean(teacher, teacher_cond, x, s), x_t, sigma_t, sigma_u)
            with self._target.to_module(self.actor_network):
                target = self._consistency(self.policy.encode(obs), x_u, sigma_u)
        consistency = pseudo_huber(self._consistency(cond, x_t, sigma_t) - target, self.huber_delta)

        from_schedule = math.ceil(n / 2)
        sigma = torch.cat(
            [
                sampler.schedule.at(torch.rand(from_schedule, device=device) * _DSM_SCHEDULE_SPAN),
                (torch.randn(n - from_schedule, device=device) * 1.2 - 1.2).exp(),
            ]
        ).clamp(sampler.sigma_min, sampler.sigma_max)
        sigma = sigma.to(x1.dtype)
        noisy = x1 + sigma.reshape(-1, 1, 1) * torch.randn_like(x1)
        weight = sampler.preconditioning.loss_weight(sigma).reshape(-1, 1, 1)
        denoising = weight * pseudo_huber(self._consistency(cond, noisy, sigma) - x1, self.huber_delta)
        err = consistency + self.dsm_weight * denoising
        return err, {
            "consistency_term": self._valid_mean(consistency, valid),
            "denoising_term": self._valid_mean(denoising, valid),
        }
