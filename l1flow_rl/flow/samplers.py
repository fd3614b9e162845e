"""Chunk samplers: turn a trained network into an action chunk, counting network evaluations.

A sampler is told what the network predicts (``prediction``) so that a loss can refuse an actor
whose sampler does not match its training target, and a trained network can be re-scored only under
samplers that read its output the same way (:func:`samplers_for`, :func:`check_sampler_fits`).
"""

from __future__ import annotations

import abc
import inspect
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import torch
from torch import Tensor

from l1flow_rl.flow.diffusion_schedule import DiffusionSchedule
from l1flow_rl.flow.time import velocity_from_sample

__all__ = [
    "PREDICTIONS",
    "ChunkSampler",
    "DDIMSampler",
    "DDPMSampler",
    "Denoiser",
    "DirectSampler",
    "EulerSampler",
    "SamplerMismatchError",
    "TwoStepSampler",
    "VelocityEulerSampler",
    "check_sampler_fits",
    "make_sampler",
    "sampler_name",
    "sampler_names",
    "sampler_parameters",
    "sampler_problems",
    "samplers_for",
]

#: what a network can be trained to predict: the clean chunk (L1 Flow), the flow velocity, the
#: diffusion noise, or the chunk directly without noise or time (regression)
PREDICTIONS = ("sample", "velocity", "epsilon", "direct")

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

    def training_signature(self) -> dict[str, Any]:
        """What the network must have been trained for to be sampled by this sampler: the prediction
        type, plus (diffusion) the training schedule's length, which its timestep input indexes."""
        return {"prediction": self.prediction}

    def settings(self) -> dict[str, Any]:
        """The constructor arguments that reproduce this sampler (``make_sampler(name, **settings)``)."""
        return {k: v for k, v in vars(self).items() if not k.startswith("_")}

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

    def training_signature(self) -> dict[str, Any]:
        return {"prediction": self.prediction, "num_train_timesteps": self.num_train_timesteps}

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


class SamplerMismatchError(ValueError):
    """A sampler was asked to read a network trained for another target."""


def sampler_names() -> list[str]:
    return sorted(_REGISTRY)


def sampler_name(sampler: ChunkSampler) -> str:
    """The registry name of a sampler (its class name for a sampler defined elsewhere)."""
    for name, cls in _REGISTRY.items():
        if type(sampler) is cls:
            return name
    return type(sampler).__name__


def samplers_for(prediction: str) -> list[str]:
    """Names of the samplers that read a network trained to predict ``prediction``.

    Example:
        >>> samplers_for("epsilon")
        ['ddim', 'ddpm']
    """
    if prediction not in PREDICTIONS:
        raise ValueError(f"unknown prediction {prediction!r}; expected one of {list(PREDICTIONS)}")
    return sorted(name for name, cls in _REGISTRY.items() if cls.prediction == prediction)


def sampler_parameters(name: str) -> list[str]:
    """The keyword arguments sampler ``name`` accepts (``policy.sampler_kwargs`` keys)."""
    cls = _sampler_class(name)
    return [p for p in inspect.signature(cls.__init__).parameters if p != "self"]


def sampler_problems(name: str, kwargs: Mapping[str, Any] | None, field: str = "policy.sampler") -> list[str]:
    """What is wrong with sampler ``name`` and its keyword arguments, one line each naming
    ``<field>`` or ``<field>_kwargs.<key>``: an unknown name, arguments it does not take, values it
    refuses.

    Example:
        >>> sampler_problems("euler", {"t_first": 0.5})  # doctest: +ELLIPSIS
        ["policy.sampler_kwargs.t_first: sampler 'euler' takes no such argument; it takes ['steps'] ..."]
    """
    if name not in _REGISTRY:
        return [f"{field}={name!r}: expected one of {sampler_names()}"]
    kwargs = dict(kwargs or {})
    accepted = sampler_parameters(name)
    unknown = sorted(set(kwargs) - set(accepted))
    if unknown:
        return [
            f"{field}_kwargs.{k}: sampler {name!r} takes no such argument; it takes {accepted} "
            f"(drop it with ~{field}_kwargs.{k})"
            for k in unknown
        ]
    try:
        _REGISTRY[name](**kwargs)
    except (TypeError, ValueError) as err:
        return [f"{field}_kwargs={kwargs}: {err}"]
    return []


def _sampler_class(name: str) -> type[ChunkSampler]:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown sampler {name!r}; expected one of {sampler_names()}") from None


def check_sampler_fits(trained: ChunkSampler, candidate: ChunkSampler) -> None:
    """Raise :class:`SamplerMismatchError` unless ``candidate`` can sample the network that
    ``trained`` was built for; the message lists the samplers that fit.

    Example:
        >>> check_sampler_fits(DDPMSampler(), DDIMSampler(16))  # same epsilon network: fine
        >>> try:
        ...     check_sampler_fits(TwoStepSampler(), DDIMSampler(16))
        ... except SamplerMismatchError as err:
        ...     print(err)  # doctest: +ELLIPSIS
        sampler 'ddim' reads an 'epsilon'-prediction network, ... samplers that fit: ['euler', 'two_step']
    """
    want, got = trained.training_signature(), candidate.training_signature()
    if want["prediction"] != got["prediction"]:
        raise SamplerMismatchError(
            f"sampler {sampler_name(candidate)!r} reads an {got['prediction']!r}-prediction network, "
            f"but this network was trained for {want['prediction']!r} prediction (sampled by "
            f"{sampler_name(trained)!r}); samplers that fit: {samplers_for(want['prediction'])}"
        )
    diffs = [f"{k}={got.get(k)!r} (trained with {v!r})" for k, v in want.items() if got.get(k) != v]
    if diffs:
        raise SamplerMismatchError(
            f"sampler {sampler_name(candidate)!r} does not fit the network's training: {', '.join(diffs)}"
        )


def make_sampler(spec: str | ChunkSampler, **kwargs: Any) -> ChunkSampler:
    """Sampler by name: ``two_step``, ``euler``, ``velocity_euler``, ``ddpm``, ``ddim`` or ``direct``.

    An argument the sampler does not take is an error naming it and the ones it takes.
    """
    if isinstance(spec, ChunkSampler):
        return spec
    cls = _sampler_class(spec)
    accepted = sampler_parameters(spec)
    unknown = sorted(set(kwargs) - set(accepted))
    if unknown:
        raise ValueError(
            f"sampler {spec!r} takes no argument {unknown} (policy.sampler_kwargs); it takes {accepted}"
        )
    return cls(**kwargs)
