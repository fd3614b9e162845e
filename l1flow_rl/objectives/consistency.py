"""Consistency Policy (Prasad et al. 2024): consistency distillation of an EDM teacher.

Departures from CP's released code (Aaditya-Prasad/consistency-policy), on purpose:

- the stop level enters as an offset of the observation condition that is zero at sigma_min; CP
  concatenates the stop's time embedding to the UNet's FiLM condition (zero-initialised weights);
- the distance is iCT's pseudo-Huber ``sqrt(d^2 + delta^2) - delta``; CP's ``Huber_Loss`` squares the
  squared error first (``sqrt(d^4 + delta^2) - delta``);
- the denoising term's log-normal half is clipped to [sigma_min, sigma_max] like its schedule half;
- the student has no dropout (CP: 0.2 on the FiLM scale and bias of the student only);
- sampling starts from ``sigma_max * noise``, the level the student trains at; CP starts from unit
  noise (its "reducing initial variance").
"""

from __future__ import annotations

import copy
import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import Tensor, nn

from l1flow_rl.flow.karras import heun_step, ict_delta, pseudo_huber, trajectory_jump
from l1flow_rl.networks.unet1d import SinusoidalEmbedding
from l1flow_rl.objectives.distillation import DistillationLossBase
from l1flow_rl.utils.doc_examples import distillation_example

__all__ = ["ConsistencyLoss", "StopLevelCondition"]

#: Consistency Policy's denoising term draws half its levels from the first 70 % of the rho schedule
#: (counted from sigma_max) and half from EDM's log-normal
_DSM_SCHEDULE_SPAN = 0.7
#: the stop level's time scaling before its embedding (CP's 1000 on c_noise = ln(sigma) / 4)
_STOP_TIME_SCALE = 1000.0


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

    ``trajectory=True`` is CP's released objective, CTM's: the student jumps from sigma_t to any stop
    level sigma_s (bin s uniform in [t, bins], the last meaning sigma_min), ``G(x, t, s) = (s/t) x +
    (1 - s/t) f(x, t; s)``; the teacher's Heun step goes to bin u (uniform in [t, s], at most one bin past
    t); the student's ``G(x_t, t, s)`` and the target's ``G(x_u, u, s)`` are both taken on to sigma_min by
    the target network, and compared there (the student's side keeps its gradient through the jump's
    input). The shared network takes one time input, so the stop level enters through the observation
    condition: a learned offset of the stop's ``c_noise`` embedding (:class:`StopLevelCondition`),
    exactly zero at sigma_min, so the deployed policy (which always stops at sigma_min) needs none of it.
    Its sampler must be built with ``trajectory=True``. Without it (the default) every jump stops at
    sigma_min: the consistency-model case (CP's ``ctm_to_cm``), compared directly.

    The target network is an exponential moving average of the student, updated at the start of each
    call with ``target_decay`` (CP's released recipe: 0, the student itself without gradient). The
    student starts from the teacher's weights; with ``freeze_encoder`` (CP's warm start) its observation
    encoder stays at the teacher's and only the denoiser trains.

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
        trajectory: bool = False,
        huber_delta: float | None = None,
        freeze_encoder: bool = True,
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
        self.freeze_encoder = bool(freeze_encoder)
        if self.freeze_encoder:
            policy.encoder.requires_grad_(False)
        self.huber_delta = huber_delta or ict_delta(policy.pred_horizon * policy.action_dim)
        self.sampler = policy.sampler
        self._check_student_sampler(trajectory=trajectory)
        self.trajectory = bool(trajectory)
        # The target network's parameters: a detached copy, moved towards the student's each call.
        self.__dict__["_target"] = self.actor_network_params.data.clone()
        if self.trajectory:
            device = next(policy.net.parameters()).device
            cond_dim = policy.obs_horizon * policy.encoder.feature_dim
            self.stop_level = StopLevelCondition(cond_dim, self.sampler.sigma_min).to(device)
            self.target_stop_level = copy.deepcopy(self.stop_level).requires_grad_(False)

    @classmethod
    def student_sampler_problem(cls, sampler, loss_kwargs):
        trajectory = bool(loss_kwargs.get("trajectory", False))
        if getattr(sampler, "trajectory", trajectory) != trajectory:
            return (
                f"policy.loss_kwargs.trajectory={trajectory}, but the student's sampler has trajectory="
                f"{sampler.trajectory}; give both the same (policy.sampler_kwargs.trajectory={trajectory})"
            )
        return None

    # -- the target network ------------------------------------------------------------------
    def _target_leaves(self) -> list[tuple[Tensor, Tensor]]:
        pairs = list(zip(self._target.values(True, True), self.actor_network_params.data.values(True, True)))
        if self.trajectory:
            own = [p.detach() for p in self.stop_level.parameters()]
            pairs += list(zip(self.target_stop_level.parameters(), own, strict=True))
        return pairs

    def extra_parameters(self) -> list[torch.nn.Parameter]:
        return list(self.stop_level.parameters()) if self.trajectory else []

    @torch.no_grad()
    def update_target(self) -> None:
        """target <- decay * target + (1 - decay) * student (floating leaves; others copied)."""
        for target, live in self._target_leaves():
            if target.is_floating_point() and self.target_decay > 0:
                target.lerp_(live, 1.0 - self.target_decay)
            else:
                target.copy_(live)

    def training_state(self) -> dict[str, Tensor]:
        state = {f"target.{k}": v for k, v in self._target.flatten_keys(".").items()}
        if self.trajectory:
            for name in ("stop_level", "target_stop_level"):
                state.update({f"{name}.{k}": v for k, v in getattr(self, name).state_dict().items()})
        return state

    def load_training_state(self, state: dict[str, Tensor]) -> None:
        for key, value in self._target.flatten_keys(".").items():
            value.copy_(state[f"target.{key}"])
        if self.trajectory:
            for name in ("stop_level", "target_stop_level"):
                n = len(name) + 1
                getattr(self, name).load_state_dict(
                    {k[n:]: v for k, v in state.items() if k[:n] == f"{name}."}
                )

    # -- the loss -----------------------------------------------------------------------------
    def _jump(
        self, cond: Tensor, x: Tensor, sigma: Tensor, stop: Tensor | None, target: bool = False
    ) -> Tensor:
        """G(x, sigma, stop): the consistency function, or with ``trajectory`` CTM's jump to ``stop``
        (None: sigma_min). ``target``: the target network's stop-level condition."""
        if not self.trajectory:
            return self.sampler.preconditioning.denoise(
                lambda xin, c: self.policy.denoise(xin, c, cond), x, sigma
            )
        stop = torch.full_like(sigma, self.sampler.sigma_min) if stop is None else stop
        offset = (self.target_stop_level if target else self.stop_level)(stop).to(cond.dtype)
        shifted = cond + offset
        denoised = self.sampler.preconditioning.denoise(
            lambda xin, c: self.policy.denoise(xin, c, shifted), x, sigma
        )
        return trajectory_jump(x, denoised, sigma, stop)

    def _pairs(self, n: int, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
        """Bins (t, s, u): CP's discretisation. Bin ``bins`` stands for sigma_min (as bin bins - 1)."""
        bins = self.sampler.bins
        t = torch.randint(0, bins - 1 if not self.trajectory else bins, (n,), device=device)
        if not self.trajectory:  # the consistency-model case: one bin on, stop at sigma_min
            return t, torch.full_like(t, bins), t + 1
        s = t + (torch.rand(n, device=device) * (bins + 1 - t)).long()
        u = t + (torch.rand(n, device=device) * (s - t + 1)).long()
        return t, s, torch.minimum(u, t + 1)

    def _distill_loss(
        self, obs: TensorDictBase, cond: Tensor, teacher_cond: Tensor, x1: Tensor, valid: Tensor | None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        self.update_target()
        n, device, sampler = x1.shape[0], x1.device, self.sampler
        levels = sampler.bin_sigmas(device=device).to(x1.dtype)
        levels = torch.cat([levels, levels[-1:]])  # bin `bins`: sigma_min
        t, s, u = self._pairs(n, device)
        sigma_t, sigma_s, sigma_u = levels[t], levels[s], levels[u]
        x_t = x1 + sigma_t.reshape(-1, 1, 1) * torch.randn_like(x1)
        pred = self._jump(cond, x_t, sigma_t, sigma_s)
        with torch.no_grad():
            view, teacher = self.teacher_view, self.teacher
            x_u = heun_step(lambda x, lv: view.clean(teacher, teacher_cond, x, lv), x_t, sigma_t, sigma_u)
        with self._target.to_module(self.actor_network):
            target_cond = self.policy.encode(obs).detach()
            with torch.no_grad():
                target = self._jump(target_cond, x_u, sigma_u, sigma_s, target=True)
            if self.trajectory:  # both on to sigma_min by the target network, the student's with its gradient
                pred = self._jump(target_cond, pred, sigma_s, None, target=True)
                with torch.no_grad():
                    target = self._jump(target_cond, target, sigma_s, None, target=True)
        consistency = pseudo_huber(pred - target, self.huber_delta)

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
        denoising = weight * pseudo_huber(self._jump(cond, noisy, sigma, None) - x1, self.huber_delta)
        err = consistency + self.dsm_weight * denoising
        return err, {
            "consistency_term": self._valid_mean(consistency, valid),
            "denoising_term": self._valid_mean(denoising, valid),
        }


class StopLevelCondition(nn.Module):
    """The stop level of a trajectory jump as an offset to the observation condition:
    ``e(s) - e(sigma_min)``, with e an MLP on the sinusoidal embedding of ``1000 ln(s) / 4`` (the student's
    own time scaling, as CP's), its last layer zero at the start. Exactly zero at sigma_min, so the
    deployed policy, which always stops there, runs without it."""

    def __init__(self, cond_dim: int, sigma_min: float, embed_dim: int = 64) -> None:
        super().__init__()
        self.sigma_min = float(sigma_min)
        self.embed = SinusoidalEmbedding(embed_dim)
        self.mlp = nn.Sequential(
            nn.Linear(embed_dim, 4 * embed_dim), nn.Mish(), nn.Linear(4 * embed_dim, cond_dim)
        )
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, stop: Tensor) -> Tensor:
        levels = torch.cat([stop.float(), stop.new_full((1,), self.sigma_min, dtype=torch.float32)])
        e = self.mlp(self.embed(levels.log() / 4 * _STOP_TIME_SCALE))
        return e[:-1] - e[-1:]
