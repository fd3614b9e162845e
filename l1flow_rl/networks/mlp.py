"""An MLP chunk denoiser over the flattened chunk, at the scale of the RL anchors' flow policies.

Facts from the anchors: QC (ColinQiyangLi/qc) and FQL (seohongpark/fql) model their flow as an MLP of
4 x 512 Dense layers with GELU, optionally followed by LayerNorm, over the concatenation
``[observation, flattened action chunk, t]`` (QC can feed ``t`` through Fourier features); the output
layer is a plain Dense to the flattened chunk. Here the observation is the encoded history (the
same global condition the UNet gets), ``t`` goes through the UNet's sinusoidal embedding (raw ``t``
times ``timestep_scale``), and LayerNorm is on by default.

``residual=False`` (the default) is the anchors' plain stack: ``Linear -> act -> LayerNorm`` per hidden
width, then ``Linear`` to ``H * A``. ``residual=True`` is a pre-norm residual stack: ``Linear`` to the
first width, then per further width ``h + Linear(act(LayerNorm(h)))`` (a projection where the width
changes), then ``act(LayerNorm(h)) -> Linear`` to ``H * A``. Both have ``len(hidden_dims) + 1`` Linear
layers.

Unlike the UNet, the MLP is built for one chunk length (``horizon``): every step of the chunk is an
input of the first layer.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn

from l1flow_rl.networks.unet1d import SinusoidalEmbedding

__all__ = ["ACTIVATIONS", "MLPDenoiser"]

#: ``activation`` -> the module class (FQL and QC: GELU; Diffusion Policy's UNet: Mish)
ACTIVATIONS: dict[str, type[nn.Module]] = {"gelu": nn.GELU, "mish": nn.Mish}


class _ResidualBlock(nn.Module):
    def __init__(self, d_in: int, d_out: int, activation: type[nn.Module], layer_norm: bool) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(d_in) if layer_norm else nn.Identity()
        self.act = activation()
        self.linear = nn.Linear(d_in, d_out)
        self.skip = nn.Identity() if d_in == d_out else nn.Linear(d_in, d_out, bias=False)

    def forward(self, h: Tensor) -> Tensor:
        return self.skip(h) + self.linear(self.act(self.norm(h)))


class MLPDenoiser(nn.Module):
    """Predicts a chunk [B, H, A] from a noisy chunk, a timestep and a global condition, as
    :class:`~l1flow_rl.networks.unet1d.ConditionalUnet1D` does, with one MLP over the flattened chunk.

    Args:
        action_dim: A.
        horizon: H, the chunk length the network is built for.
        global_cond_dim: size of the flattened observation features (0: unconditional).
        hidden_dims: the hidden widths (QC and FQL: 4 x 512).
        timestep_embed_dim: size of the sinusoidal timestep features fed to the first layer; 0 builds
            a timestep-free network (plain regression), whose ``forward`` must get ``t=None``.
        timestep_scale: t is multiplied by it before the embedding (as the UNet's).
        activation: ``gelu`` (QC, FQL) or ``mish`` (Diffusion Policy's UNet).
        layer_norm: LayerNorm in every hidden layer.
        residual: the pre-norm residual stack instead of the plain one (see the module's docstring).

    Example:
        >>> net = MLPDenoiser(2, horizon=16, global_cond_dim=10, hidden_dims=(64, 64))
        >>> net(torch.randn(3, 16, 2), torch.rand(3), torch.randn(3, 10)).shape
        torch.Size([3, 16, 2])
    """

    #: any chunk length the network was built for works (the UNet's is a power of two)
    horizon_multiple = 1

    def __init__(
        self,
        action_dim: int,
        horizon: int,
        global_cond_dim: int,
        hidden_dims: Sequence[int] = (512, 512, 512, 512),
        timestep_embed_dim: int = 64,
        timestep_scale: float = 1.0,
        activation: str = "gelu",
        layer_norm: bool = True,
        residual: bool = False,
    ) -> None:
        super().__init__()
        hidden_dims = tuple(int(d) for d in hidden_dims)
        if not hidden_dims or min(hidden_dims) < 1:
            raise ValueError(f"hidden_dims must name at least one positive width, got {list(hidden_dims)}")
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation {activation!r}: expected one of {sorted(ACTIVATIONS)}")
        if not timestep_scale > 0:
            raise ValueError(f"timestep_scale must be positive, got {timestep_scale}")
        if action_dim < 1 or horizon < 1 or global_cond_dim < 0:
            raise ValueError(
                f"action_dim={action_dim} and horizon={horizon} must be >= 1, "
                f"global_cond_dim={global_cond_dim} >= 0"
            )
        self.action_dim, self.horizon, self.global_cond_dim = int(action_dim), int(horizon), global_cond_dim
        self.hidden_dims, self.activation = hidden_dims, activation
        self.layer_norm, self.residual = bool(layer_norm), bool(residual)
        self.timestep_embed_dim, self.timestep_scale = int(timestep_embed_dim), float(timestep_scale)
        self.time_embed = SinusoidalEmbedding(timestep_embed_dim) if timestep_embed_dim else None
        d_in = horizon * action_dim + timestep_embed_dim + global_cond_dim
        act = ACTIVATIONS[activation]
        norm = nn.LayerNorm if layer_norm else nn.Identity
        if residual:
            blocks: list[nn.Module] = [nn.Linear(d_in, hidden_dims[0])]
            blocks += [_ResidualBlock(a, b, act, layer_norm) for a, b in itertools.pairwise(hidden_dims)]
            blocks += [norm(hidden_dims[-1]), act()]
        else:
            blocks = []
            for a, b in itertools.pairwise((d_in, *hidden_dims)):
                blocks += [nn.Linear(a, b), act(), norm(b)]
        self.body = nn.Sequential(*blocks)
        self.head = nn.Linear(hidden_dims[-1], horizon * action_dim)

    def settings(self) -> dict[str, Any]:
        """The constructor's settings beyond the data's sizes: what rebuilds this network."""
        return {
            "hidden_dims": list(self.hidden_dims),
            "timestep_embed_dim": self.timestep_embed_dim,
            "timestep_scale": self.timestep_scale,
            "activation": self.activation,
            "layer_norm": self.layer_norm,
            "residual": self.residual,
        }

    def forward(self, x: Tensor, t: Tensor | None, global_cond: Tensor | None = None) -> Tensor:
        """x: [B, H, A]; t: [B] or a scalar (None when built without a timestep); global_cond: [B, C]."""
        if x.dim() != 3 or tuple(x.shape[1:]) != (self.horizon, self.action_dim):
            raise ValueError(
                f"MLP input must be [B, {self.horizon}, {self.action_dim}] (built for chunks of "
                f"{self.horizon} steps), got {tuple(x.shape)}"
            )
        n = x.shape[0]
        parts = [x.reshape(n, -1)]
        if self.time_embed is not None:
            if t is None:
                raise ValueError("this MLP was built with a timestep embedding; pass t")
            t = t.expand(n) if t.dim() == 0 else t
            parts.append(self.time_embed(t * self.timestep_scale if self.timestep_scale != 1.0 else t))
        elif t is not None:
            raise ValueError(
                "this MLP was built without a timestep embedding (timestep_embed_dim=0); pass t=None"
            )
        if self.global_cond_dim:
            if global_cond is None or global_cond.shape != (n, self.global_cond_dim):
                got = None if global_cond is None else tuple(global_cond.shape)
                raise ValueError(f"global_cond must be [{n}, {self.global_cond_dim}], got {got}")
            parts.append(global_cond)
        h = torch.cat([p.to(x.dtype) for p in parts], dim=-1)
        return self.head(self.body(h)).reshape(n, self.horizon, self.action_dim)
