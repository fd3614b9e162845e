"""Karras et al. (2022, EDM) noise levels and preconditioning, shared by the EDM policy, its Heun
sampler and the students distilled from it (Consistency Policy, OneDP).

The chunk at noise level sigma is ``x = x0 + sigma * n`` (``n ~ N(0, I)``, ``x0`` the normalised chunk in
[-1, 1]). The network F never sees ``x`` or sigma raw: the denoiser is

    D(x, sigma) = c_skip(sigma) x + c_out(sigma) F(c_in(sigma) x, c_noise(sigma))

with EDM's ``c_skip = sd^2 / (sigma^2 + sd^2)``, ``c_out = sigma sd / sqrt(sigma^2 + sd^2)``,
``c_in = 1 / sqrt(sigma^2 + sd^2)`` and ``c_noise = ln(sigma) / 4`` (``sd``: sigma_data). ``c_noise``
is the time value the network takes, through the same path as every other method: the UNet multiplies
it by ``network.timestep_scale`` before its sinusoidal embedding (1000 in the EDM configs, so the
network sees ``250 ln(sigma)``, Consistency Policy's scaling).

With ``boundary=True`` the skip and output scalings are Consistency Policy's, shifted by sigma_min:
``c_skip = sd^2 / ((sigma - sigma_min)^2 + sd^2)`` and ``c_out = (sigma - sigma_min) sd / sqrt(sigma^2 +
sd^2)``, so ``D(x, sigma_min) = x`` whatever the network: the consistency boundary condition.

sigma_data: actions are normalised to [-1, 1]; 0.5 is EDM's image default and the value Consistency
Policy uses for actions, close to the standard deviation of a uniform spread over [-1, 1] (0.577). It
is a field, so a task whose actions sit elsewhere can say so.

Example:
    >>> k = KarrasPreconditioning(sigma_data=0.5)
    >>> [round(float(c), 4) for c in k.scalings(torch.tensor(0.5))]
    [0.5, 0.3536, 1.4142, -0.1733]
    >>> KarrasSchedule(sigma_min=0.002, sigma_max=80.0, rho=7.0).sigmas(3).tolist()
    [80.0, 2.515..., 0.002...]
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "KarrasPreconditioning",
    "KarrasSchedule",
    "RawNet",
    "heun_step",
    "ict_delta",
    "pseudo_huber",
    "trajectory_jump",
]

#: one raw network evaluation F(x_in, c_noise) [B, H, A] (the observation condition is bound)
RawNet = Callable[[Tensor, Tensor], Tensor]


def _per_sample(sigma: Tensor, like: Tensor) -> Tensor:
    """sigma ([] or [B]) shaped to broadcast against ``like`` [B, ...]."""
    if sigma.dim() == 0:
        return sigma
    return sigma.reshape(sigma.shape[0], *([1] * (like.dim() - 1)))


@dataclass(frozen=True)
class KarrasPreconditioning:
    """The EDM scalings for ``sigma_data`` (and Consistency Policy's boundary form when ``boundary``)."""

    sigma_data: float = 0.5
    boundary: bool = False
    sigma_min: float = 0.002

    def __post_init__(self) -> None:
        if not self.sigma_data > 0:
            raise ValueError(f"sigma_data must be positive, got {self.sigma_data}")
        if not self.sigma_min > 0:
            raise ValueError(f"sigma_min must be positive, got {self.sigma_min}")

    def scalings(self, sigma: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(c_skip, c_out, c_in, c_noise) at ``sigma`` (same shape as ``sigma``)."""
        sd2 = self.sigma_data**2
        norm = (sigma.square() + sd2).sqrt()
        shifted = sigma - self.sigma_min if self.boundary else sigma
        c_skip = sd2 / (shifted.square() + sd2)
        c_out = shifted * self.sigma_data / norm
        return c_skip, c_out, 1.0 / norm, sigma.log() / 4.0

    def denoise(self, net: RawNet, x: Tensor, sigma: Tensor) -> Tensor:
        """D(x, sigma): the clean chunk the preconditioned network predicts from ``x`` at ``sigma``
        ([] or [B])."""
        sigma = sigma.to(x.dtype).expand(x.shape[0]) if sigma.dim() == 0 else sigma.to(x.dtype)
        c_skip, c_out, c_in, c_noise = (_per_sample(c, x) for c in self.scalings(sigma))
        return c_skip * x + c_out * net(c_in * x, c_noise.reshape(-1))

    def loss_weight(self, sigma: Tensor) -> Tensor:
        """EDM's lambda(sigma) = (sigma^2 + sd^2) / (sigma sd)^2: unit loss at every sigma at init."""
        return (sigma.square() + self.sigma_data**2) / (sigma * self.sigma_data).square()


@dataclass(frozen=True)
class KarrasSchedule:
    """EDM's noise levels,
    ``sigma_i = (sigma_max^(1/rho) + i/(n-1) (sigma_min^(1/rho) - sigma_max^(1/rho)))^rho``."""

    sigma_min: float = 0.002
    sigma_max: float = 80.0
    rho: float = 7.0

    def __post_init__(self) -> None:
        if not 0 < self.sigma_min < self.sigma_max:
            raise ValueError(
                f"noise levels need 0 < sigma_min < sigma_max, got sigma_min={self.sigma_min}, "
                f"sigma_max={self.sigma_max}"
            )
        if not self.rho > 0:
            raise ValueError(f"rho must be positive, got {self.rho}")

    def at(self, position: Tensor) -> Tensor:
        """sigma at ``position`` in [0, 1] along the schedule (0: sigma_max, 1: sigma_min)."""
        lo, hi = self.sigma_min ** (1 / self.rho), self.sigma_max ** (1 / self.rho)
        return (hi + position * (lo - hi)).pow(self.rho).clamp(self.sigma_min, self.sigma_max)

    def sigmas(self, n: int, *, device: torch.device | str = "cpu") -> Tensor:
        """The ``n`` levels from sigma_max down to sigma_min (float64 maths, float32 result)."""
        if n < 1:
            raise ValueError(f"the schedule needs at least 1 level, got {n}")
        if n == 1:
            return torch.tensor([self.sigma_max], device=device)
        positions = torch.arange(n, dtype=torch.float64) / (n - 1)
        return self.at(positions).float().to(device)


def heun_step(
    denoiser: Callable[[Tensor, Tensor], Tensor],
    x: Tensor,
    sigma: Tensor,
    next_sigma: Tensor,
    *,
    to_zero: bool = False,
) -> Tensor:
    """One step of EDM's Heun solver of the probability-flow ODE dx/dsigma = (x - D(x, sigma)) / sigma,
    from ``sigma`` to ``next_sigma`` ([] or [B] each): an Euler step, corrected by the slope at its end
    unless the step ends at 0 (``to_zero``; said by the caller, so that no value is read back): 2
    evaluations of ``denoiser(x, sigma)``, 1 for the last step to 0."""
    s, s_next = _per_sample(sigma, x), _per_sample(next_sigma, x)
    slope = (x - denoiser(x, sigma)) / s
    euler = x + (s_next - s) * slope
    if to_zero:
        return euler
    end_slope = (euler - denoiser(euler, next_sigma)) / s_next
    return x + (s_next - s) * (slope + end_slope) / 2


def trajectory_jump(x: Tensor, denoised: Tensor, sigma: Tensor, stop: Tensor) -> Tensor:
    """CTM's jump from ``x`` at ``sigma`` to level ``stop`` (each [] or [B]) given the network's clean
    estimate ``denoised``: ``(stop / sigma) x + (1 - stop / sigma) denoised``. ``stop = sigma`` leaves x
    where it is; a stop near 0 lands on the estimate.

    >>> trajectory_jump(torch.ones(1, 2), torch.zeros(1, 2), torch.tensor(4.0), torch.tensor(1.0)).tolist()
    [[0.25, 0.25]]
    """
    ratio = _per_sample(stop / sigma, x)
    return ratio * x + (1 - ratio) * denoised


def pseudo_huber(diff: Tensor, delta: float) -> Tensor:
    """``sqrt(diff^2 + delta^2) - delta``, element-wise: quadratic below ``delta``, linear above (iCT).

    >>> pseudo_huber(torch.tensor([0.0, 3.0]), 4.0).tolist()
    [0.0, 1.0]
    """
    return (diff.square() + delta**2).sqrt() - delta


def ict_delta(numel: int) -> float:
    """iCT's pseudo-Huber delta for data of ``numel`` values, 0.00054 sqrt(numel) (also CP's)."""
    return 0.00054 * math.sqrt(numel)
