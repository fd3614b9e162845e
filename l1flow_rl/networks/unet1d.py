"""Diffusion Policy's 1-D conditional temporal UNet with FiLM conditioning.

Layout (facts from Diffusion Policy): residual blocks of Conv1d -> GroupNorm(8) -> Mish, twice,
with FiLM scale and bias after the first conv; stride-2 conv down, transposed conv up; the
timestep goes through a sinusoidal embedding and an MLP and is concatenated with the global
(observation) condition.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn

__all__ = ["ConditionalUnet1D", "SinusoidalEmbedding"]


class SinusoidalEmbedding(nn.Module):
    """Transformer-style sin/cos features of a scalar (flow time in [0, 1] or an integer diffusion step)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        if dim < 4 or dim % 2:
            raise ValueError(f"embedding dim must be even and >= 4, got {dim}")
        half = dim // 2
        freqs = torch.exp(torch.arange(half) * -(math.log(10000.0) / (half - 1)))
        self.register_buffer("freqs", freqs, persistent=False)

    def forward(self, t: Tensor) -> Tensor:
        angles = t.float()[:, None] * self.freqs[None, :]
        return torch.cat([angles.sin(), angles.cos()], dim=-1)


class _ConvBlock(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, kernel_size: int, n_groups: int) -> None:
        super().__init__(
            nn.Conv1d(c_in, c_out, kernel_size, padding=kernel_size // 2),
            nn.GroupNorm(n_groups, c_out),
            nn.Mish(),
        )


class _FiLMResidualBlock(nn.Module):
    def __init__(self, c_in: int, c_out: int, cond_dim: int, kernel_size: int, n_groups: int) -> None:
        super().__init__()
        self.block1 = _ConvBlock(c_in, c_out, kernel_size, n_groups)
        self.block2 = _ConvBlock(c_out, c_out, kernel_size, n_groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * c_out))
        self.residual = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: Tensor, cond: Tensor) -> Tensor:
        h = self.block1(x)
        scale, bias = self.film(cond).unsqueeze(-1).chunk(2, dim=1)
        h = self.block2(scale * h + bias)
        return h + self.residual(x)


class ConditionalUnet1D(nn.Module):
    """Predicts a chunk [B, H, A] from a noisy chunk, a timestep and a global condition.

    Args:
        action_dim: A, the channels of the chunk.
        global_cond_dim: size of the flattened observation features.
        down_dims: channel widths per level (Diffusion Policy: 256/512/1024; ManiSkill state: 64/128/256).
        timestep_embed_dim: size of the sinusoidal timestep embedding; 0 builds a timestep-free
            network (plain regression), whose ``forward`` must get ``t=None``.
        kernel_size: the conv kernel (5 in Diffusion Policy).
        n_groups: the GroupNorm groups (8 in Diffusion Policy).
        timestep_scale: t is multiplied by it before the sinusoidal embedding. 1 (default) feeds the
            raw flow time in [0, 1], as the official L1 Flow code does; there the embedding's fastest
            feature turns by one radian over the whole path, so the network barely resolves t. 1000
            spreads [0, 1] over the range Diffusion Policy's integer steps use.

    The chunk length must be divisible by ``2 ** (len(down_dims) - 1)``.
    """

    def __init__(
        self,
        action_dim: int,
        global_cond_dim: int,
        down_dims: Sequence[int] = (256, 512, 1024),
        timestep_embed_dim: int = 128,
        kernel_size: int = 5,
        n_groups: int = 8,
        timestep_scale: float = 1.0,
    ) -> None:
        super().__init__()
        if not timestep_scale > 0:
            raise ValueError(f"timestep_scale must be positive, got {timestep_scale}")
        self.timestep_scale = float(timestep_scale)
        down_dims = tuple(int(d) for d in down_dims)
        if not down_dims:
            raise ValueError("down_dims must name at least one level")
        bad = [d for d in down_dims if d % n_groups]
        if bad:
            raise ValueError(f"down_dims {down_dims}: every width must be divisible by n_groups={n_groups}")
        self.action_dim, self.global_cond_dim, self.down_dims = action_dim, global_cond_dim, down_dims
        self.timestep_embed_dim, self.kernel_size, self.n_groups = timestep_embed_dim, kernel_size, n_groups
        if timestep_embed_dim:
            d = timestep_embed_dim
            self.time_mlp: nn.Module | None = nn.Sequential(
                SinusoidalEmbedding(d), nn.Linear(d, 4 * d), nn.Mish(), nn.Linear(4 * d, d)
            )
        else:
            self.time_mlp = None
        cond_dim = timestep_embed_dim + global_cond_dim
        if cond_dim == 0:
            raise ValueError("the UNet needs a timestep embedding or a global condition")

        def res(c_in: int, c_out: int) -> _FiLMResidualBlock:
            return _FiLMResidualBlock(c_in, c_out, cond_dim, kernel_size, n_groups)

        widths = (action_dim, *down_dims)
        self.down = nn.ModuleList()
        for i, (c_in, c_out) in enumerate(itertools.pairwise(widths)):
            last = i == len(down_dims) - 1
            sample = nn.Identity() if last else nn.Conv1d(c_out, c_out, 3, stride=2, padding=1)
            self.down.append(nn.ModuleList([res(c_in, c_out), res(c_out, c_out), sample]))
        self.mid = nn.ModuleList([res(down_dims[-1], down_dims[-1]), res(down_dims[-1], down_dims[-1])])
        self.up = nn.ModuleList()
        # As in Diffusion Policy, every up level upsamples and the finest down level's skip is unused.
        for c_in, c_out in reversed(list(itertools.pairwise(down_dims))):
            sample = nn.ConvTranspose1d(c_in, c_in, 4, stride=2, padding=1)
            self.up.append(nn.ModuleList([res(2 * c_out, c_in), res(c_in, c_in), sample]))
        self.head = nn.Sequential(
            _ConvBlock(down_dims[0], down_dims[0], kernel_size, n_groups),
            nn.Conv1d(down_dims[0], action_dim, 1),
        )
        self.horizon_multiple = 2 ** (len(down_dims) - 1)

    def settings(self) -> dict[str, Any]:
        """The constructor's settings beyond the data's sizes: what rebuilds this network."""
        return {
            "down_dims": list(self.down_dims),
            "timestep_embed_dim": self.timestep_embed_dim,
            "timestep_scale": self.timestep_scale,
            "kernel_size": self.kernel_size,
            "n_groups": self.n_groups,
        }

    def forward(self, x: Tensor, t: Tensor | None, global_cond: Tensor | None = None) -> Tensor:
        """x: [B, H, A]; t: [B] (or None when built without a timestep); global_cond: [B, C]."""
        if x.dim() != 3 or x.shape[-1] != self.action_dim:
            raise ValueError(f"UNet input must be [B, H, {self.action_dim}], got {tuple(x.shape)}")
        if x.shape[1] % self.horizon_multiple:
            raise ValueError(
                f"chunk length {x.shape[1]} must be divisible by {self.horizon_multiple} "
                f"for down_dims={self.down_dims}"
            )
        feats = []
        if self.time_mlp is not None:
            if t is None:
                raise ValueError("this UNet was built with a timestep embedding; pass t")
            t = t.expand(x.shape[0]) if t.dim() == 0 else t
            feats.append(self.time_mlp(t * self.timestep_scale if self.timestep_scale != 1.0 else t))
        elif t is not None:
            raise ValueError(
                "this UNet was built without a timestep embedding (timestep_embed_dim=0); pass t=None"
            )
        if self.global_cond_dim:
            if global_cond is None or global_cond.shape != (x.shape[0], self.global_cond_dim):
                got = None if global_cond is None else tuple(global_cond.shape)
                raise ValueError(f"global_cond must be [{x.shape[0]}, {self.global_cond_dim}], got {got}")
            feats.append(global_cond)
        cond = torch.cat(feats, dim=-1)

        h = x.transpose(1, 2)
        skips = []
        for block1, block2, down in self.down:
            h = block2(block1(h, cond), cond)
            skips.append(h)
            h = down(h)
        for block in self.mid:
            h = block(h, cond)
        for block1, block2, up in self.up:
            h = torch.cat([h, skips.pop()], dim=1)
            h = up(block2(block1(h, cond), cond))
        return self.head(h).transpose(1, 2)
