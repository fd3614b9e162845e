"""OneDP-D (Wang et al. 2024): a deterministic one-step generator distilled from a diffusion teacher by
the KL divergence along the diffusion chain."""

from __future__ import annotations

from typing import ClassVar

import torch
from tensordict import TensorDictBase
from torch import Tensor

from l1flow_rl.flow.samplers import sampler_name
from l1flow_rl.objectives.distillation import DistillationLossBase
from l1flow_rl.utils.doc_examples import distillation_example

__all__ = ["OneDPDLoss"]


@distillation_example("DDPMSampler()", "OneStepDDPMSampler(stochastic=False)", 1, scale=1.0)
class OneDPDLoss(DistillationLossBase):
    """The generator G (the actor, one NFE) is pushed to where the teacher's diffusion chain puts mass.

    Each batch: the generator's chunk ``A = G(z, obs)`` is noised to a teacher level (EDM: EDM's
    log-normal sigma; DDPM: a uniform step in [2, 95] of 100), ``x_k = fwd(A, n, k)``. The gradient of
    KL(p_G(x_k) || p_teacher(x_k)) with respect to A is ``w(k) (s_G(x_k) - s_teacher(x_k)) dx_k/dA``
    with OneDP's ``w(k) = sigma_k^2``; in the networks' clean-chunk estimates this is ``fake(x_k) -
    teacher(x_k)`` for EDM and ``alpha_bar_k (fake - teacher)`` for DDPM
    (:meth:`~l1flow_rl.objectives.distillation.TeacherView.kl_weight`). For this deterministic generator
    (z = 0, OneDP-D) the distribution of x_k is a Gaussian around A, so its estimate is A itself and no
    score network is needed (OneDP-S, :class:`~l1flow_rl.objectives.onedp_s.OneDPSLoss`, learns it). The
    gradient g is applied as that of ``0.5 |A - sg(A - g)|^2``, whose value is ``0.5 g^2``.

    The student's sampler (``onedp_edm`` or ``onedp_ddpm``) must read the network the way the teacher is
    parameterised; the generator starts from the teacher's weights. OneDP trains it with Adam at lr 1e-6,
    betas (0, 0.999): ``policy=onedp_d`` sets ``train.lr`` and ``train.betas`` so.

    Returns ``"loss_onedp"`` and the detached diagnostic ``"generator_term"``.
    """

    loss_name = "loss_onedp"
    prediction = "generator"
    sampler_hint = "L1FlowActor.for_state(..., sampler=OneStepEDMSampler(stochastic=False))"
    diagnostic_keys: tuple[str, ...] = ("generator_term",)
    teacher_predictions = ("karras", "epsilon")
    #: whether the generator reads noise (OneDP-S) or zeros (OneDP-D)
    stochastic: ClassVar[bool] = False

    def _setup(self) -> None:
        sampler, teacher_sampler = self.policy.sampler, self.teacher.sampler
        if sampler.teacher_prediction != teacher_sampler.prediction:  # type: ignore[attr-defined]
            raise ValueError(
                f"the generator's sampler {sampler_name(sampler)!r} reads a network parameterised like a "
                f"{sampler.teacher_prediction!r} teacher, but the teacher samples with "  # type: ignore[attr-defined]
                f"{sampler_name(teacher_sampler)!r} ({teacher_sampler.prediction!r}); use "
                f"{'onedp_edm' if teacher_sampler.prediction == 'karras' else 'onedp_ddpm'}"
            )
        steps = getattr(teacher_sampler, "num_train_timesteps", None)
        if steps is not None and steps != sampler.num_train_timesteps:  # type: ignore[attr-defined]
            raise ValueError(
                f"the generator reads a {sampler.num_train_timesteps}-step DDPM network, the teacher was "  # type: ignore[attr-defined]
                f"trained with {steps} steps (policy.sampler_kwargs.num_train_timesteps)"
            )
        self._check_student_sampler()

    @classmethod
    def student_sampler_problem(cls, sampler, loss_kwargs):
        if getattr(sampler, "stochastic", cls.stochastic) != cls.stochastic:
            return (
                f"{cls.__name__} trains a {'stochastic' if cls.stochastic else 'deterministic'} generator; "
                f"build its sampler with stochastic={cls.stochastic} (policy.sampler_kwargs.stochastic)"
            )
        return None

    def _fake_clean(self, obs: TensorDictBase, generated: Tensor, noisy: Tensor, level: Tensor) -> Tensor:
        """The generator distribution's clean-chunk estimate at ``noisy``: the chunk itself here."""
        return generated

    def _extra_terms(self, obs: TensorDictBase, generated: Tensor) -> tuple[Tensor | None, dict[str, Tensor]]:
        return None, {}

    def _distill_loss(
        self, obs: TensorDictBase, cond: Tensor, teacher_cond: Tensor, x1: Tensor, valid: Tensor | None
    ) -> tuple[Tensor, dict[str, Tensor]]:
        sampler, view = self.policy.sampler, self.teacher_view
        z = sampler.latent(x1)  # type: ignore[attr-defined]
        generated = sampler.generate(lambda x, t: self.policy.denoise(x, t, cond), z)  # type: ignore[attr-defined]
        with torch.no_grad():
            sample = generated.detach()
            level = view.distillation_levels(x1.shape[0], x1.device)
            noisy = view.add_noise(sample, torch.randn_like(sample), level)
            real = view.clean(self.teacher, teacher_cond, noisy, level)
            fake = self._fake_clean(obs, sample, noisy, level)
            step = view.kl_weight(level, sample) * (fake - real)
        generator_term = 0.5 * (generated - (generated - step).detach()).square()
        extra, diagnostics = self._extra_terms(obs, sample)
        err = generator_term if extra is None else generator_term + extra
        return err, {"generator_term": self._valid_mean(generator_term, valid), **diagnostics}
