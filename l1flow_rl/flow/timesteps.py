"""Training-time distributions over the flow time t in [0, 1] (t = 0 is noise)."""

from __future__ import annotations

import abc

import torch
from torch import Tensor

__all__ = [
    "BetaTimesteps",
    "MixedLogitNormalTimesteps",
    "TimestepDistribution",
    "UniformTimesteps",
    "make_timesteps",
]


class TimestepDistribution(abc.ABC):
    """Draws ``n`` flow times; pass a ``torch.Generator`` for reproducible draws."""

    @abc.abstractmethod
    def sample(
        self, n: int, *, device: torch.device | str = "cpu", generator: torch.Generator | None = None
    ) -> Tensor: ...

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v}" for k, v in vars(self).items())
        return f"{type(self).__name__}({args})"


class UniformTimesteps(TimestepDistribution):
    """t ~ U(0, 1)."""

    def sample(self, n, *, device="cpu", generator=None):
        return torch.rand(n, device=device, generator=generator)


class MixedLogitNormalTimesteps(TimestepDistribution):
    """L1 Flow's default: t = sigmoid(N(mean, std)), replaced by U(0, 1) with probability ``p_uniform``.

    The logit-normal concentrates training near t = 0.5, where the two-step sampler queries the
    network; the small uniform share keeps the ends of [0, 1] covered.
    """

    def __init__(self, mean: float = 0.0, std: float = 1.0, p_uniform: float = 0.01) -> None:
        if not 0.0 <= p_uniform <= 1.0:
            raise ValueError(f"p_uniform must lie in [0, 1], got {p_uniform}")
        if std <= 0:
            raise ValueError(f"std must be positive, got {std}")
        self.mean, self.std, self.p_uniform = mean, std, p_uniform

    def sample(self, n, *, device="cpu", generator=None):
        logit = torch.randn(n, device=device, generator=generator) * self.std + self.mean
        t = torch.sigmoid(logit)
        uniform = torch.rand(n, device=device, generator=generator)
        use_uniform = torch.rand(n, device=device, generator=generator) < self.p_uniform
        return torch.where(use_uniform, uniform, t)


class BetaTimesteps(TimestepDistribution):
    """pi0-style: t = cutoff * Beta(alpha, beta). Beta(1, 1.5) puts more mass near t = 0, the noisy end."""

    def __init__(self, alpha: float = 1.0, beta: float = 1.5, cutoff: float = 0.999) -> None:
        if alpha <= 0 or beta <= 0:
            raise ValueError(f"Beta parameters must be positive, got alpha={alpha}, beta={beta}")
        if not 0.0 < cutoff <= 1.0:
            raise ValueError(f"cutoff must lie in (0, 1], got {cutoff}")
        self.alpha, self.beta, self.cutoff = alpha, beta, cutoff

    def sample(self, n, *, device="cpu", generator=None):
        # Beta via two Gammas, because torch.distributions cannot take a Generator.
        a = torch._standard_gamma(torch.full((n,), self.alpha, device=device), generator=generator)
        b = torch._standard_gamma(torch.full((n,), self.beta, device=device), generator=generator)
        return self.cutoff * a / (a + b)


_REGISTRY: dict[str, type[TimestepDistribution]] = {
    "uniform": UniformTimesteps,
    "mixed": MixedLogitNormalTimesteps,
    "logit_normal": MixedLogitNormalTimesteps,
    "beta": BetaTimesteps,
}


def make_timesteps(spec: str | TimestepDistribution, **kwargs: float) -> TimestepDistribution:
    """Build a distribution by name (``uniform``, ``mixed``, ``beta``) or pass one through."""
    if isinstance(spec, TimestepDistribution):
        return spec
    try:
        cls = _REGISTRY[spec]
    except KeyError:
        raise ValueError(
            f"unknown timestep distribution {spec!r}; expected one of {sorted(_REGISTRY)}"
        ) from None
    return cls(**kwargs)
