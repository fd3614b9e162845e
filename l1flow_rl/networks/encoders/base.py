"""The encoder interface: a TensorDict of observation entries [N, To, ...] -> per-step features [N, To, F].

The policy flattens the To per-step features into the UNet's global condition. An entry whose
per-step shape has one dim is a flat (low-dimensional) vector; three dims [3, H, W] is an image,
stored and passed around as uint8 and turned into floats by the image encoder on its own device.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping

from tensordict import TensorDictBase
from torch import Tensor, nn

__all__ = ["ObservationEncoder", "image_entries", "is_image_shape", "vector_entries"]


def is_image_shape(shape: tuple[int, ...]) -> bool:
    """A per-step shape [C, H, W] is an image entry; [D] is a flat vector."""
    return len(shape) == 3


def image_entries(obs_shapes: Mapping[str, tuple[int, ...]]) -> dict[str, tuple[int, int, int]]:
    """The image entries of ``obs_shapes`` (per-step [C, H, W]), in their declared order."""
    return {k: tuple(s) for k, s in obs_shapes.items() if is_image_shape(tuple(s))}  # type: ignore[misc]


def vector_entries(obs_shapes: Mapping[str, tuple[int, ...]]) -> dict[str, int]:
    """The flat entries of ``obs_shapes`` (per-step [D]) as entry -> D, in their declared order."""
    return {k: int(s[0]) for k, s in obs_shapes.items() if len(s) == 1}


class ObservationEncoder(nn.Module, abc.ABC):
    """Interface: ``obs_shapes`` (entry -> per-step shape) and ``feature_dim`` (F).

    ``forward`` takes a TensorDict of batch [N, To] holding every entry of ``obs_shapes`` (flat
    entries already normalised by the policy, images as uint8) and returns [N, To, F].
    """

    obs_shapes: dict[str, tuple[int, ...]]
    feature_dim: int

    @abc.abstractmethod
    def forward(self, obs: TensorDictBase) -> Tensor:
        """[N, To, ...] entries -> [N, To, F]."""
