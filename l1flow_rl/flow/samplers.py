"""Chunk samplers: turn a trained network into an action chunk, counting network evaluations.

A sampler is told what the network predicts (``prediction``) so that a loss can refuse an actor
whose sampler does not match its training target.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import ClassVar

import torch
from torch import Tensor

from l1flow_rl.flow.diffusion_schedule import DiffusionSchedule
from l1flow_rl.flow.time import velocity_from_sample

__all__ = [
    "ChunkSampler",
    "DDIMSampler",
    "DDPMSampler",
    "Denoiser",
    "DirectSampler",
    "EulerSampler",
    "TwoStepSampler",
    "VelocityEulerSampler",
    "make_sampler",
]

#: ``denoise(x, t)``: one network evaluation on the current chunk ``x`` [B, H, A] at time ``t`` [B]
#: (flow time in [0, 1], or the integer diffusion step; ``None`` for timestep-free regression).
Denoiser = Callable[[Tensor, Tensor | None], Tensor]


class ChunkSampler(abc.ABC):
    """Base class. ``prediction`` names the network's training target."""

    prediction: ClassVar[str]
    uses_timestep: ClassVar[bool] = True

    @property
    @abc.abstractmethod
    def nfe(self) -> int:
        """Network evaluations per chunk."""

    @abc.abstractmethod
    def __call__(
        self,
        denoise: Denoiser,
        x_init: Tensor,
        *,
        deterministic: bool = False,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Integrate from the initial chunk ``x_init`` (noise, or zeros when deterministic)."""

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v}" for k, v in vars(self).items() if not k.startswith("_"))
        return f"{type(self).__name__}({args})"


def _full(x: Tensor, value: float) -> Tensor:
    return torch.full((x.shape[0],), float(value), device=x.device, dtype=x.dtype)


class TwoStepSampler(ChunkSampler):
    """L1 Flow inference, 2 NFE: one Euler step from t=0 to ``t_first``, then f(x_{t_first}, t_first)."""

    prediction = "sample"

    def __init__(self, t_first: float = 0.5) -> None:
        if not 0.0 < t_first < 1.0:
            raise ValueError(f"t_first must lie strictly inside (0, 1), got {t_first}")
        self.t_first = float(t_first)

    @property
    def nfe(self) -> int:
        return 2

    def __call__(self, denoise, x_init, *, deterministic=False, generator=None):
        t0 = _full(x_init, 0.0)
        x = x_init + self.t_first * velocity_from_sample(denoise(x_init, t0), x_init, t0)
        return denoise(x, _full(x_init, self.t_first))


class _UniformEuler(ChunkSampler):
    """``steps`` uniform Euler steps from t=0 to t=1; subclasses say how the network gives a velocity."""

    def __init__(self, steps: int = 10) -> None:
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        self.steps = int(steps)

    @property
    def nfe(self) -> int:
        return self.steps

    @abc.abstractmethod
    def _velocity(self, output: Tensor, x: Tensor, t: Tensor) -> Tensor: ...

    def __call__(self, denoise, x_init, *, deterministic=False, generator=None):
        x, dt = x_init, 1.0 / self.steps
        for i in range(self.steps):
            t = _full(x, i * dt)
            x = x + dt * self._velocity(denoise(x, t), x, t)
        return x


class EulerSampler(_UniformEuler):
    """n uniform Euler steps for a sample-prediction network, using v = (f - x_t) / (1 - t)."""

    prediction = "sample"

    def _velocity(self, output, x, t):
        return velocity_from_sample(output, x, t)


class VelocityEulerSampler(_UniformEuler):
    """n uniform Euler steps for a v-prediction flow-matching network."""

    prediction = "velocity"

    def _velocity(self, output, x, t):
        return output


class DirectSampler(ChunkSampler):
    """Plain regression: a single evaluation on a zero chunk, with no timestep."""

    prediction = "direct"
    uses_timestep = False

    @property
    def nfe(self) -> int:
        return 1

    def __call__(self, denoise, x_init, *, deterministic=False, generator=None):
        return denoise(torch.zeros_like(x_init), None)


class _EpsilonSampler(ChunkSampler):
    prediction = "epsilon"

    def __init__(self, num_train_timesteps: int = 100, clip_sample: bool = True) -> None:
        self.num_train_timesteps = int(num_train_timesteps)
        self.clip_sample = clip_sample
        self._schedule = DiffusionSchedule(num_train_timesteps)

    @property
    def schedule(self) -> DiffusionSchedule:
        return self._schedule

    def _predict_x0(self, x: Tensor, eps: Tensor, alpha_bar: Tensor) -> Tensor:
        x0 = (x - (1 - alpha_bar).sqrt() * eps) / alpha_bar.sqrt()
        return x0.clamp(-1.0, 1.0) if self.clip_sample else x0


class DDPMSampler(_EpsilonSampler):
    """Ancestral DDPM with epsilon prediction, clipped x0 and the 'fixed_small' variance (one NFE a step)."""

    @property
    def nfe(self) -> int:
        return self.num_train_timesteps

    def __call__(self, denoise, x_init, *, deterministic=False, generator=None):
        ac = self.schedule.alphas_cumprod.to(x_init.device)
        x = x_init
        for step in reversed(range(self.num_train_timesteps)):
            a_t = ac[step]
            a_prev = ac[step - 1] if step > 0 else torch.ones((), device=x.device)
            alpha_t = a_t / a_prev
            eps = denoise(x, _full(x, step))
            x0 = self._predict_x0(x, eps, a_t)
            mean = (a_prev.sqrt() * (1 - alpha_t) * x0 + alpha_t.sqrt() * (1 - a_prev) * x) / (1 - a_t)
            if step > 0 and not deterministic:
                var = ((1 - a_prev) / (1 - a_t) * (1 - alpha_t)).clamp_min(1e-20)
                noise = torch.randn(x.shape, device=x.device, dtype=x.dtype, generator=generator)
                mean = mean + var.sqrt() * noise
            x = mean
        return x


class DDIMSampler(_EpsilonSampler):
    """Deterministic DDIM (eta = 0) over ``steps`` evenly spaced ('leading') diffusion steps."""

    def __init__(self, steps: int = 16, num_train_timesteps: int = 100, clip_sample: bool = True) -> None:
        super().__init__(num_train_timesteps, clip_sample)
        if not 1 <= steps <= num_train_timesteps:
            raise ValueError(f"steps must lie in [1, {num_train_timesteps}], got {steps}")
        self.steps = int(steps)

    @property
    def nfe(self) -> int:
        return self.steps

    def timesteps(self) -> list[int]:
        stride = self.num_train_timesteps // self.steps
        return [i * stride for i in reversed(range(self.steps))]

    def __call__(self, denoise, x_init, *, deterministic=False, generator=None):
        ac = self.schedule.alphas_cumprod.to(x_init.device)
        stride = self.num_train_timesteps // self.steps
        x = x_init
        for step in self.timesteps():
            a_t = ac[step]
            a_prev = ac[step - stride] if step - stride >= 0 else torch.ones((), device=x.device)
            eps = denoise(x, _full(x, step))
            x0 = self._predict_x0(x, eps, a_t)
            x = a_prev.sqrt() * x0 + (1 - a_prev).sqrt() * eps
        return x


_REGISTRY: dict[str, type[ChunkSampler]] = {
    "two_step": TwoStepSampler,
    "euler": EulerSampler,
    "velocity_euler": VelocityEulerSampler,
    "ddpm": DDPMSampler,
    "ddim": DDIMSampler,
    "direct": DirectSampler,
}


def make_sampler(spec: str | ChunkSampler, **kwargs: float) -> ChunkSampler:
    """Sampler by name: ``two_step``, ``euler``, ``velocity_euler``, ``ddpm``, ``ddim`` or ``direct``."""
    if isinstance(spec, ChunkSampler):
        return spec
    try:
        cls = _REGISTRY[spec]
    except KeyError:
        raise ValueError(f"unknown sampler {spec!r}; expected one of {sorted(_REGISTRY)}") from None
    return cls(**kwargs)
