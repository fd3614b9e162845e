"""The DDPM noise schedule (squaredcos_cap_v2) that Diffusion Policy trains and samples with.

Written here rather than imported from diffusers so the core install stays small; tests check it
step for step against diffusers' DDPMScheduler and DDIMScheduler.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["DiffusionSchedule"]


class DiffusionSchedule:
    """Cumulative-alpha table for ``num_train_timesteps`` discrete diffusion steps.

    Diffusion time runs the other way from flow time: step 0 is nearly clean, step T-1 is noise.
    """

    def __init__(self, num_train_timesteps: int = 100, beta_schedule: str = "squaredcos_cap_v2") -> None:
        if num_train_timesteps < 1:
            raise ValueError(f"num_train_timesteps must be >= 1, got {num_train_timesteps}")
        self.num_train_timesteps = num_train_timesteps
        self.beta_schedule = beta_schedule
        if beta_schedule == "squaredcos_cap_v2":
            betas = self._cosine_betas(num_train_timesteps)
        elif beta_schedule == "linear":
            betas = torch.linspace(1e-4, 0.02, num_train_timesteps, dtype=torch.float64)
        else:
            raise ValueError(
                f"unknown beta_schedule {beta_schedule!r}; expected 'squaredcos_cap_v2' or 'linear'"
            )
        self.betas = betas.float()
        self.alphas_cumprod = torch.cumprod(1.0 - betas, dim=0).float()

    @staticmethod
    def _cosine_betas(n: int, max_beta: float = 0.999) -> Tensor:
        def alpha_bar(s: float) -> float:
            return math.cos((s + 0.008) / 1.008 * math.pi / 2) ** 2

        betas = [min(1 - alpha_bar((i + 1) / n) / alpha_bar(i / n), max_beta) for i in range(n)]
        return torch.tensor(betas, dtype=torch.float64)

    def alpha_bar(self, steps: Tensor) -> Tensor:
        """Cumulative alpha at integer ``steps``; a negative step means 'before step 0' (alpha_bar = 1)."""
        table = self.alphas_cumprod.to(steps.device)
        return torch.where(steps >= 0, table[steps.clamp_min(0)], torch.ones((), device=steps.device))

    def add_noise(self, x0: Tensor, noise: Tensor, steps: Tensor) -> Tensor:
        """Forward process: sqrt(a) x0 + sqrt(1 - a) noise, with ``steps`` of shape [B]."""
        a = self.alpha_bar(steps).reshape(-1, *([1] * (x0.dim() - 1)))
        return a.sqrt() * x0 + (1 - a).sqrt() * noise
