"""Chunk samplers: turn a trained network into an action chunk, counting network evaluations.

A sampler is told what the network predicts (``prediction``) so that a loss can refuse an actor
whose sampler does not match its training target, and a trained network can be re-scored only under
samplers that read its output the same way (:func:`samplers_for`, :func:`check_sampler_fits`).
"""

from __future__ import annotations

import abc
import inspect
import itertools
import math
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import torch
from torch import Tensor

from l1flow_rl.flow.diffusion_schedule import DiffusionSchedule
from l1flow_rl.flow.karras import KarrasPreconditioning, KarrasSchedule, heun_step, trajectory_jump
from l1flow_rl.flow.time import velocity_from_sample

__all__ = [
    "PREDICTIONS",
    "ChunkSampler",
    "ConsistencySampler",
    "DDIMSampler",
    "DDPMSampler",
    "Denoiser",
    "DirectSampler",
    "EDMHeunSampler",
    "EulerSampler",
    "OneStepDDPMSampler",
    "OneStepEDMSampler",
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
#: ... and the distillation family: EDM's preconditioned denoiser ("karras"), a consistency function
#: ("consistency", Consistency Policy) and a one-step generator ("generator", OneDP)
PREDICTIONS += ("karras", "consistency", "generator")

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

    @property
    def inner_noise_draws(self) -> int:
        """Chunk-shaped noise draws the sampler makes after its start (ancestral DDPM, a chained
        Consistency Policy); 0: a chunk is a function of its start noise alone. A sampler that draws
        takes them as ``inner_noise`` [B, draws, H, A] when given, so that a chunk is reproducible."""
        return 0

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


def _inner_draw(
    k: int, like: Tensor, deterministic: bool, generator: torch.Generator | None, inner_noise: Tensor | None
) -> Tensor:
    """The sampler's ``k``-th noise draw after its start: given (``inner_noise[:, k]``), zeros when
    deterministic, else fresh."""
    if inner_noise is not None:
        return inner_noise[:, k].to(like.dtype)
    if deterministic:
        return torch.zeros_like(like)
    return torch.randn(like.shape, device=like.device, dtype=like.dtype, generator=generator)


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

    @property
    def inner_noise_draws(self) -> int:
        return self.num_train_timesteps - 1  # one per step but the last

    def __call__(self, denoise, x_init, *, deterministic=False, generator=None, inner_noise=None):
        ac = self.schedule.alphas_cumprod.to(x_init.device)
        x = x_init
        for k, step in enumerate(reversed(range(self.num_train_timesteps))):
            a_t = ac[step]
            a_prev = ac[step - 1] if step > 0 else torch.ones((), device=x.device)
            alpha_t = a_t / a_prev
            eps = denoise(x, _full(x, step))
            x0 = self._predict_x0(x, eps, a_t)
            mean = (a_prev.sqrt() * (1 - alpha_t) * x0 + alpha_t.sqrt() * (1 - a_prev) * x) / (1 - a_t)
            if step > 0 and (inner_noise is not None or not deterministic):
                var = ((1 - a_prev) / (1 - a_t) * (1 - alpha_t)).clamp_min(1e-20)
                mean = mean + var.sqrt() * _inner_draw(k, x, deterministic, generator, inner_noise)
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


class _KarrasLevels(ChunkSampler):
    """Noise levels on EDM's rho schedule and the preconditioning the network was trained under."""

    boundary: ClassVar[bool] = False

    def __init__(
        self,
        steps: int,
        sigma_min: float,
        sigma_max: float,
        rho: float,
        sigma_data: float,
        clip_denoised: bool,
    ) -> None:
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        self.steps = int(steps)
        self.sigma_min, self.sigma_max, self.rho = float(sigma_min), float(sigma_max), float(rho)
        self.sigma_data = float(sigma_data)
        self.clip_denoised = bool(clip_denoised)
        self._schedule = KarrasSchedule(self.sigma_min, self.sigma_max, self.rho)
        self._precond = KarrasPreconditioning(self.sigma_data, self.boundary, self.sigma_min)

    @property
    def schedule(self) -> KarrasSchedule:
        return self._schedule

    @property
    def preconditioning(self) -> KarrasPreconditioning:
        return self._precond

    def training_signature(self) -> dict[str, Any]:
        signature = {"prediction": self.prediction, "sigma_data": self.sigma_data}
        if self.boundary:  # the boundary condition sits at sigma_min, so the net learnt that one
            signature["sigma_min"] = self.sigma_min
        return signature

    def _denoiser(self, denoise: Denoiser) -> Callable[[Tensor, Tensor], Tensor]:
        def clean(x: Tensor, sigma: Tensor) -> Tensor:
            out = self._precond.denoise(denoise, x, sigma)
            return out.clamp(-1.0, 1.0) if self.clip_denoised else out

        return clean


class EDMHeunSampler(_KarrasLevels):
    """EDM's deterministic sampler (Karras et al. 2022, Algorithm 1 without churn): ``steps`` (N) Heun
    steps over ``sigma_max -> ... -> sigma_min -> 0``, starting from ``sigma_max * noise``. Each step
    costs 2 evaluations except the last one to sigma = 0, an Euler step: NFE = 2N - 1 (EDM's 35 NFE is
    N = 18, 19 NFE is N = 10, 1 NFE is N = 1). ``clip_denoised`` clips each denoised estimate to the
    action range, as Diffusion Policy clips its x0 (and Consistency Policy its EDM teacher)."""

    prediction = "karras"

    def __init__(
        self,
        steps: int = 18,
        sigma_min: float = 0.002,
        sigma_max: float = 80.0,
        rho: float = 7.0,
        sigma_data: float = 0.5,
        clip_denoised: bool = True,
    ) -> None:
        super().__init__(steps, sigma_min, sigma_max, rho, sigma_data, clip_denoised)

    @property
    def nfe(self) -> int:
        return 2 * self.steps - 1

    def __call__(self, denoise, x_init, *, deterministic=False, generator=None):
        levels = self.schedule.sigmas(self.steps, device=x_init.device).to(x_init.dtype)
        levels = torch.cat([levels, levels.new_zeros(1)])
        clean = self._denoiser(denoise)
        x = x_init * levels[0]
        for i, (sigma, next_sigma) in enumerate(itertools.pairwise(levels)):
            x = heun_step(clean, x, sigma, next_sigma, to_zero=i == self.steps - 1)
        return x


class ConsistencySampler(_KarrasLevels):
    """Consistency Policy's sampler: one jump of the consistency function from ``sigma_max * noise`` to
    the clean chunk, then ``steps - 1`` times: renoise to an intermediate level and jump again (one NFE
    each). The intermediate levels are bins ``ceil(k * bins / steps)`` of the ``bins``-level rho
    schedule, k = 1 .. steps - 1: CP's bins 27 and 54 of 80 for 3 steps (its README's reading; its code's
    ``['D', 27, 54]`` passes them on as raw sigma). Deterministic: no renoising (zero noise throughout).
    ``trajectory``: the network was trained with CP's trajectory objective, so each jump to sigma_min is
    CTM's, ``(sigma_min / sigma) x + (1 - sigma_min / sigma) f(x, sigma)``."""

    prediction = "consistency"
    boundary = True

    def __init__(
        self,
        steps: int = 1,
        bins: int = 80,
        sigma_min: float = 0.02,
        sigma_max: float = 80.0,
        rho: float = 7.0,
        sigma_data: float = 0.5,
        clip_denoised: bool = True,
        trajectory: bool = False,
    ) -> None:
        super().__init__(steps, sigma_min, sigma_max, rho, sigma_data, clip_denoised)
        self.trajectory = bool(trajectory)
        if bins < 2:
            raise ValueError(f"bins must be >= 2, got {bins}")
        if steps > bins:
            raise ValueError(f"steps={steps} exceeds the {bins} bins of the schedule")
        self.bins = int(bins)

    @property
    def nfe(self) -> int:
        return self.steps

    def bin_sigmas(self, *, device: torch.device | str = "cpu") -> Tensor:
        """The ``bins`` training levels, sigma_max first (CP's discretisation)."""
        return self.schedule.sigmas(self.bins, device=device)

    def training_signature(self) -> dict[str, Any]:
        return {**super().training_signature(), "trajectory": self.trajectory}

    def _denoiser(self, denoise: Denoiser) -> Callable[[Tensor, Tensor], Tensor]:
        if not self.trajectory:
            return super()._denoiser(denoise)
        stop = torch.tensor(self.sigma_min)

        def jump(x: Tensor, sigma: Tensor) -> Tensor:
            out = trajectory_jump(x, self._precond.denoise(denoise, x, sigma), sigma, stop.to(x))
            return out.clamp(-1.0, 1.0) if self.clip_denoised else out

        return jump

    def chain_bins(self) -> list[int]:
        """The bins the chain renoises to after the first jump."""
        return [math.ceil(k * self.bins / self.steps) for k in range(1, self.steps)]

    @property
    def inner_noise_draws(self) -> int:
        return self.steps - 1  # one renoising per chained jump

    def __call__(self, denoise, x_init, *, deterministic=False, generator=None, inner_noise=None):
        clean = self._denoiser(denoise)
        levels = self.bin_sigmas(device=x_init.device).to(x_init.dtype)
        out = clean(x_init * self.sigma_max, levels[0])
        for k, b in enumerate(self.chain_bins()):
            noise = _inner_draw(k, out, deterministic, generator, inner_noise)
            out = clean(out + levels[b] * noise, levels[b])
        return out


class _OneStep(ChunkSampler):
    """OneDP's generator: one evaluation of a network in its teacher's parameterisation at one fixed
    noise level, on a noise chunk z (``stochastic``, OneDP-S) or on zeros (OneDP-D, a deterministic
    generator). ``teacher_prediction`` names the teacher it is distilled from."""

    prediction = "generator"
    teacher_prediction: ClassVar[str]

    def __init__(self, stochastic: bool, clip_sample: bool) -> None:
        self.stochastic = bool(stochastic)
        self.clip_sample = bool(clip_sample)

    @property
    def nfe(self) -> int:
        return 1

    @abc.abstractmethod
    def generate(self, denoise: Denoiser, z: Tensor) -> Tensor:
        """The generator's chunk from ``z`` (unclipped: what training differentiates)."""

    def training_signature(self) -> dict[str, Any]:
        """The prediction, the teacher it reads the network as, and every setting but clipping."""
        settings = {k: v for k, v in self.settings().items() if k != "clip_sample"}
        return {"prediction": self.prediction, "teacher": self.teacher_prediction, **settings}

    def latent(self, like: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """The generator's input for a chunk shaped like ``like``: noise, or zeros when deterministic."""
        if not self.stochastic:
            return torch.zeros_like(like)
        return torch.randn(like.shape, device=like.device, dtype=like.dtype, generator=generator)

    def __call__(self, denoise, x_init, *, deterministic=False, generator=None):
        z = x_init if self.stochastic else torch.zeros_like(x_init)
        out = self.generate(denoise, z)
        return out.clamp(-1.0, 1.0) if self.clip_sample else out


class OneStepEDMSampler(_OneStep):
    """A generator distilled from an EDM teacher: D(sigma_init * z, sigma_init) under EDM's
    preconditioning, so that with the teacher's weights it starts as the teacher's one-step denoiser.
    ``sigma_init`` 2.5 is OneDP's continuous-diffusion level (its Table 7)."""

    teacher_prediction = "karras"

    def __init__(
        self,
        sigma_init: float = 2.5,
        sigma_data: float = 0.5,
        stochastic: bool = True,
        clip_sample: bool = True,
    ) -> None:
        super().__init__(stochastic, clip_sample)
        if not sigma_init > 0:
            raise ValueError(f"sigma_init must be positive, got {sigma_init}")
        self.sigma_init, self.sigma_data = float(sigma_init), float(sigma_data)
        self._precond = KarrasPreconditioning(self.sigma_data)

    def generate(self, denoise, z):
        sigma = torch.full((z.shape[0],), self.sigma_init, device=z.device, dtype=z.dtype)
        return self._precond.denoise(denoise, z * self.sigma_init, sigma)


class OneStepDDPMSampler(_OneStep):
    """A generator distilled from a DDPM teacher: its epsilon network read at the fixed step ``t_init``
    (OneDP's 65 of 100) as ``x0 = (z - sqrt(1 - a) eps) / sqrt(a)``."""

    teacher_prediction = "epsilon"

    def __init__(
        self,
        t_init: int = 65,
        num_train_timesteps: int = 100,
        stochastic: bool = True,
        clip_sample: bool = True,
    ) -> None:
        super().__init__(stochastic, clip_sample)
        if not 0 <= t_init < num_train_timesteps:
            raise ValueError(f"t_init must lie in [0, {num_train_timesteps}), got {t_init}")
        self.t_init, self.num_train_timesteps = int(t_init), int(num_train_timesteps)
        self._schedule = DiffusionSchedule(num_train_timesteps)

    @property
    def schedule(self) -> DiffusionSchedule:
        return self._schedule

    def generate(self, denoise, z):
        a = self.schedule.alphas_cumprod[self.t_init].to(z.device, z.dtype)
        eps = denoise(z, _full(z, self.t_init))
        return (z - (1 - a).sqrt() * eps) / a.sqrt()


_REGISTRY: dict[str, type[ChunkSampler]] = {
    "two_step": TwoStepSampler,
    "euler": EulerSampler,
    "velocity_euler": VelocityEulerSampler,
    "ddpm": DDPMSampler,
    "ddim": DDIMSampler,
    "direct": DirectSampler,
    "edm_heun": EDMHeunSampler,
    "edm_consistency": ConsistencySampler,
    "onedp_edm": OneStepEDMSampler,
    "onedp_ddpm": OneStepDDPMSampler,
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
