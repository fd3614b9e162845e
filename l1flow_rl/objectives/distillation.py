"""What the distillation losses share: a frozen teacher actor, a student that starts from its weights,
and reading the teacher's network in the parameterisation it was trained for (EDM or DDPM).

The teacher is an :class:`~l1flow_rl.L1FlowActor` (``l1flow-rl train ... teacher=<checkpoint>`` loads
it with the safe checkpoint loader); its parameters are frozen here and never reach the optimiser.
Which teachers a loss accepts is a class attribute (``teacher_predictions``: the prediction types of
the teacher's sampler), so the config check (:mod:`l1flow_rl.objectives.teacher`) can refuse an
unfit checkpoint before any work.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import Tensor

from l1flow_rl.flow.samplers import ChunkSampler, sampler_name
from l1flow_rl.modules.policy import ChunkPolicy
from l1flow_rl.objectives.chunk_loss import ChunkLossBase
from l1flow_rl.utils.state_dict import load_state_into

__all__ = ["DistillationLossBase", "TeacherView", "teacher_view"]


class TeacherView(abc.ABC):
    """A diffusion network read in its training parameterisation: noise levels, the forward process,
    its clean-chunk estimate and its own training error (what an auxiliary score network learns by)."""

    @abc.abstractmethod
    def sample_levels(self, n: int, device: torch.device) -> Tensor:
        """Training noise levels [n] (sigma for EDM, the integer step for DDPM)."""

    def distillation_levels(self, n: int, device: torch.device) -> Tensor:
        """The levels [n] a score-distillation loss noises the generator's chunks to (OneDP's draws)."""
        return self.sample_levels(n, device)

    @abc.abstractmethod
    def kl_weight(self, level: Tensor, like: Tensor) -> Tensor:
        """The factor that turns the clean-chunk difference ``fake - real`` at ``level`` into OneDP's
        generator gradient ``w(k) (s_fake - s_real) dx_k/dA`` with ``w(k) = sigma_k^2`` (DreamFusion's
        weight, OneDP section 2.3), shaped to broadcast against ``like`` [N, H, A]."""

    @abc.abstractmethod
    def add_noise(self, x0: Tensor, noise: Tensor, level: Tensor) -> Tensor: ...

    @abc.abstractmethod
    def clean(self, policy: ChunkPolicy, cond: Tensor, x: Tensor, level: Tensor) -> Tensor:
        """The network's estimate of the clean chunk from ``x`` at ``level``."""

    @abc.abstractmethod
    def training_error(self, policy: ChunkPolicy, cond: Tensor, x0: Tensor) -> Tensor:
        """Element-wise denoising error of ``policy`` on clean chunks ``x0`` (the teacher's own loss)."""


class _KarrasView(TeacherView):
    """An EDM network: log-normal sigma (EDM's P_mean -1.2, P_std 1.2), x = x0 + sigma n."""

    def __init__(self, sampler: ChunkSampler, p_mean: float = -1.2, p_std: float = 1.2) -> None:
        self.precond = sampler.preconditioning  # type: ignore[attr-defined]
        self.p_mean, self.p_std = p_mean, p_std

    def sample_levels(self, n, device):
        return (torch.randn(n, device=device) * self.p_std + self.p_mean).exp()

    def add_noise(self, x0, noise, level):
        return x0 + level.to(x0.dtype).reshape(-1, 1, 1) * noise

    def kl_weight(self, level, like):
        # score (D - x) / sigma^2 and x = A + sigma n: sigma^2 (s_fake - s_real) = fake - real
        return like.new_ones(())

    def clean(self, policy, cond, x, level):
        return self.precond.denoise(lambda xin, c: policy.denoise(xin, c, cond), x, level.to(x.dtype))

    def training_error(self, policy, cond, x0):
        sigma = self.sample_levels(x0.shape[0], x0.device).to(x0.dtype)
        denoised = self.clean(policy, cond, self.add_noise(x0, torch.randn_like(x0), sigma), sigma)
        return self.precond.loss_weight(sigma).reshape(-1, 1, 1) * (denoised - x0).square()


class _EpsilonView(TeacherView):
    """A DDPM epsilon network (Diffusion Policy's schedule): integer steps, x0 from the predicted noise.
    Distillation draws steps in [2, T - 5] (OneDP's [2, 95] of 100, away from both ends of the chain)."""

    def __init__(self, sampler: ChunkSampler) -> None:
        self.schedule = sampler.schedule  # type: ignore[attr-defined]

    def sample_levels(self, n, device):
        return torch.randint(0, self.schedule.num_train_timesteps, (n,), device=device)

    def distillation_levels(self, n, device):
        steps = self.schedule.num_train_timesteps
        first = min(_DISTILL_FIRST_STEP, steps - 1)
        last = max(first, steps - _DISTILL_END_MARGIN)
        return torch.randint(first, last + 1, (n,), device=device)

    def add_noise(self, x0, noise, level):
        return self.schedule.add_noise(x0, noise, level)

    def kl_weight(self, level, like):
        # score -eps / sigma_k, x_k = alpha_k A + sigma_k n: sigma_k^2 (s_fake - s_real) alpha_k, read in
        # clean-chunk units (eps = (x - alpha x0) / sigma), is alpha_bar_k (fake - real)
        return self.schedule.alpha_bar(level).to(like.dtype).reshape(-1, 1, 1)

    def clean(self, policy, cond, x, level):
        a = self.schedule.alpha_bar(level).to(x.dtype).reshape(-1, 1, 1)
        eps = policy.denoise(x, level.to(x.dtype), cond)
        return (x - (1 - a).sqrt() * eps) / a.sqrt()

    def training_error(self, policy, cond, x0):
        steps = self.sample_levels(x0.shape[0], x0.device)
        noise = torch.randn_like(x0)
        eps = policy.denoise(self.add_noise(x0, noise, steps), steps.to(x0.dtype), cond)
        return (eps - noise).square()


#: OneDP's distillation steps of a DDPM teacher: [2, 95] of 100, i.e. [2, T - 5]
_DISTILL_FIRST_STEP, _DISTILL_END_MARGIN = 2, 5

#: prediction type of a diffusion network -> how to read it
_VIEWS = {"karras": _KarrasView, "epsilon": _EpsilonView}


def teacher_view(sampler: ChunkSampler) -> TeacherView:
    """How to read a network sampled by ``sampler`` (EDM ``karras`` or DDPM ``epsilon`` prediction)."""
    try:
        return _VIEWS[sampler.prediction](sampler)
    except KeyError:
        raise ValueError(
            f"a {sampler.prediction!r}-prediction network (sampler {sampler_name(sampler)!r}) cannot teach; "
            f"teachers are {sorted(_VIEWS)}-prediction networks"
        ) from None


class DistillationLossBase(ChunkLossBase):
    """A loss that trains its actor (the student) against a frozen ``teacher`` actor.

    Subclasses set ``teacher_predictions`` (the teacher sampler prediction types they can distil) and
    implement :meth:`_distill_loss`, which gets the flat observation (the teacher encodes it with its
    own encoder and normalisers). With ``init_from_teacher`` (the default, as Consistency Policy and
    OneDP do) the student starts from the teacher's weights, normalisers included.
    """

    teacher_predictions: ClassVar[tuple[str, ...]] = ()

    def __init__(
        self,
        actor_network: TensorDictModule,
        *,
        teacher: TensorDictModule,
        init_from_teacher: bool = True,
        reduction: str = "mean",
        mask_padding: bool = False,
    ) -> None:
        teacher_policy = getattr(teacher, "module", None)
        if not isinstance(teacher_policy, ChunkPolicy):
            raise TypeError(f"teacher must be an L1FlowActor, got {type(teacher).__name__}")
        got = teacher_policy.sampler.prediction
        if got not in self.teacher_predictions:
            raise ValueError(
                f"{type(self).__name__} distils a {list(self.teacher_predictions)}-prediction teacher; this "
                f"teacher samples with {sampler_name(teacher_policy.sampler)!r} ({got!r} prediction)"
            )
        if init_from_teacher:
            # Before the functional copy of the parameters is made, so that copy holds these values.
            load_state_into(actor_network, teacher.state_dict(), "the teacher")
        super().__init__(actor_network, reduction=reduction, mask_padding=mask_padding)
        teacher.requires_grad_(False)
        teacher.eval()
        # Not a submodule: the teacher is no part of this loss's state (the config names its checkpoint).
        self.__dict__["_teacher"] = teacher_policy
        self.teacher_view = teacher_view(teacher_policy.sampler)
        self._setup()

    def _setup(self) -> None:
        """What a subclass builds or checks once the student and the teacher are in place."""

    @classmethod
    def student_sampler_problem(cls, sampler: ChunkSampler, loss_kwargs: dict[str, Any]) -> str | None:
        """Why the student's ``sampler`` does not fit this loss with ``loss_kwargs`` (None: it does). The
        loss raises it when built; the config check (``teacher_problems``) reports it before any work."""
        return None

    def _check_student_sampler(self, **loss_kwargs: Any) -> None:
        problem = self.student_sampler_problem(self.policy.sampler, loss_kwargs)
        if problem:
            raise ValueError(problem)

    @property
    def teacher(self) -> ChunkPolicy:
        return self.__dict__["_teacher"]

    def _elementwise_loss(self, cond, x1, valid):
        raise TypeError(f"{type(self).__name__} needs the observation; ChunkLossBase calls _chunk_loss")

    def _chunk_loss(self, obs: TensorDictBase, cond: Tensor, x1: Tensor, valid: Tensor | None):
        with torch.no_grad():
            teacher_cond = self.teacher.encode(obs)
        return self._distill_loss(obs, cond, teacher_cond, x1, valid)

    @abc.abstractmethod
    def _distill_loss(
        self, obs: TensorDictBase, cond: Tensor, teacher_cond: Tensor, x1: Tensor, valid: Tensor | None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """Element-wise loss [N, H, A] and diagnostics, given the student's and the teacher's conditions."""
