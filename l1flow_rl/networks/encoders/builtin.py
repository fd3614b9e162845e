"""Registers the built-in encoders: ``state`` and ``resnet18_gn``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from l1flow_rl.networks.encoders.base import ObservationEncoder, image_entries, vector_entries
from l1flow_rl.networks.encoders.image import ImageObservationEncoder
from l1flow_rl.networks.encoders.registry import EncoderSpec, register_encoder
from l1flow_rl.networks.encoders.state import StateEncoder

__all__: list[str] = []

#: the fields of EncoderConfig the image encoder reads (``name`` selects it)
_IMAGE_OPTIONS = (
    "feature_dim",
    "num_keypoints",
    "crop_ratio",
    "shared",
    "group_size",
    "image_norm",
    "pretrained",
    "norm_affine",
    "state_hidden_dims",
)


def _build_state(obs_shapes: Mapping[str, tuple[int, ...]], options: Mapping[str, Any]) -> ObservationEncoder:
    assert not image_entries(obs_shapes)  # make_encoder refuses images for this spec
    return StateEncoder(vector_entries(obs_shapes), hidden_dims=tuple(options.get("state_hidden_dims", ())))


def _build_resnet18_gn(
    obs_shapes: Mapping[str, tuple[int, ...]], options: Mapping[str, Any]
) -> ObservationEncoder:
    kwargs = {k: options[k] for k in _IMAGE_OPTIONS if k in options}
    if "state_hidden_dims" in kwargs:
        kwargs["state_hidden_dims"] = tuple(kwargs["state_hidden_dims"])
    return ImageObservationEncoder(obs_shapes, **kwargs)


register_encoder(EncoderSpec("state", _build_state, images=False))
register_encoder(EncoderSpec("resnet18_gn", _build_resnet18_gn, images=True))
