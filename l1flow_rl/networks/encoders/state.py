"""Observation encoders: a TensorDict of observation entries [N, To, ...] -> per-step features [N, To, F].

The policy flattens the To per-step features into the UNet's global condition. Image encoders
plug in through the same interface.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn

__all__ = ["ObservationEncoder", "StateEncoder"]


class ObservationEncoder(nn.Module, abc.ABC):
    """Interface: ``obs_shapes`` (entry -> per-step shape) and ``feature_dim`` (F)."""

    obs_shapes: dict[str, tuple[int, ...]]
    feature_dim: int

    @abc.abstractmethod
    def forward(self, obs: TensorDictBase) -> Tensor:
        """[N, To, ...] entries -> [N, To, F]."""


class StateEncoder(ObservationEncoder):
    """Concatenates flat state entries; an optional MLP (``hidden_dims``) maps them to features.

    Diffusion Policy and ManiSkill's baseline feed low-dimensional state straight into the
    condition, which is the default here (no MLP).
    """

    def __init__(
        self,
        obs_dims: Mapping[str, int],
        hidden_dims: Sequence[int] = (),
        activation: type[nn.Module] = nn.Mish,
    ) -> None:
        super().__init__()
        if not obs_dims:
            raise ValueError("StateEncoder needs at least one observation entry")
        self.obs_shapes = {k: (int(d),) for k, d in obs_dims.items()}
        in_dim = sum(d for (d,) in self.obs_shapes.values())
        layers: list[nn.Module] = []
        for h in hidden_dims:
            layers += [nn.Linear(in_dim, h), activation()]
            in_dim = h
        self.mlp = nn.Sequential(*layers)
        self.feature_dim = in_dim

    def forward(self, obs: TensorDictBase) -> Tensor:
        return self.mlp(torch.cat([obs.get(k) for k in self.obs_shapes], dim=-1))
