"""The state encoder: flat entries concatenated, optionally through an MLP."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn

from l1flow_rl.networks.encoders.base import ObservationEncoder

__all__ = ["StateEncoder"]


class StateEncoder(ObservationEncoder):
    """Concatenates flat state entries; an optional MLP (``hidden_dims``) maps them to features.

    Diffusion Policy and ManiSkill's baseline feed low-dimensional state straight into the
    condition, which is the default here (no MLP).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> enc = StateEncoder({"qpos": 3, "goal": 2})
        >>> enc(TensorDict({"qpos": torch.zeros(4, 2, 3), "goal": torch.zeros(4, 2, 2)}, [4, 2])).shape
        torch.Size([4, 2, 5])
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
