"""The encoder registry: the ``encoder`` config group's names -> builders.

An encoder is one module that calls :func:`register_encoder` and one YAML file under
``configs/encoder/``. A builder takes the observation entries (entry -> per-step shape) and the
encoder config's fields (a plain dict) and returns an :class:`ObservationEncoder`. ``"auto"`` is
not an encoder: it resolves to ``resnet18_gn`` when the observation holds an image, else ``state``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from l1flow_rl.networks.encoders.base import ObservationEncoder, image_entries
from l1flow_rl.utils.registries import register_unique

__all__ = [
    "AUTO",
    "EncoderSpec",
    "encoder_names",
    "encoder_problems",
    "get_encoder",
    "make_encoder",
    "register_encoder",
    "resolve_encoder_name",
]

AUTO = "auto"

Builder = Callable[[Mapping[str, tuple[int, ...]], Mapping[str, Any]], ObservationEncoder]


@dataclass(frozen=True)
class EncoderSpec:
    """One encoder of the config group.

    Args:
        name: the value of ``encoder.name`` (``encoder=<name>`` on the command line).
        build: ``(obs_shapes, options) -> ObservationEncoder``; ``options`` are the encoder config's
            fields (``feature_dim``, ``crop_ratio``, ...), of which it reads the ones it uses.
        images: whether it can encode image entries ([3, H, W] per step). A task whose observation
            has images is refused with an encoder that cannot, before any demonstration is made.
    """

    name: str
    build: Builder
    images: bool


_REGISTRY: dict[str, EncoderSpec] = {}


def register_encoder(spec: EncoderSpec, *, replace: bool = False) -> EncoderSpec:
    if spec.name == AUTO:
        raise ValueError(f"{AUTO!r} is reserved (it picks an encoder from the observation)")
    return register_unique(_REGISTRY, spec.name, spec, replace=replace, what="an encoder named")


def encoder_names() -> list[str]:
    """Registered encoder names (plus ``"auto"``, which picks one)."""
    return [*sorted(_REGISTRY), AUTO]


def resolve_encoder_name(name: str, has_images: bool) -> str:
    """``auto`` -> ``resnet18_gn`` for observations with images, else ``state``; others unchanged."""
    if name != AUTO:
        return name
    return "resnet18_gn" if has_images else "state"


def get_encoder(name: str) -> EncoderSpec:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(
            f"encoder.name={name!r} is not a registered encoder; known: {encoder_names()}"
        ) from None


def encoder_problems(name: str, images: Sequence[str]) -> list[str]:
    """Why encoder ``name`` (or ``auto``) cannot encode an observation whose image entries are
    ``images``: an unknown name, or a flat-only encoder given images. Empty when it can.

    Example:
        >>> encoder_problems("state", ["rgb"])  # doctest: +ELLIPSIS
        ["encoder.name='state' reads flat vectors only, but the observation has image entries ['rgb']; ..."]
    """
    try:
        spec = get_encoder(resolve_encoder_name(name, bool(images)))
    except ValueError as err:
        return [str(err)]
    if images and not spec.images:
        return [
            f"encoder.name={spec.name!r} reads flat vectors only, but the observation has image entries "
            f"{list(images)}; use an image encoder (encoder=auto or encoder=resnet18_gn)"
        ]
    return []


def make_encoder(
    name: str, obs_shapes: Mapping[str, tuple[int, ...]], options: Mapping[str, Any] | None = None
) -> ObservationEncoder:
    """Build the encoder ``name`` (or ``auto``) for the observation entries ``obs_shapes``."""
    images = image_entries(obs_shapes)
    problems = encoder_problems(name, images)
    if problems:
        raise ValueError(problems[0])
    spec = get_encoder(resolve_encoder_name(name, bool(images)))
    return spec.build(dict(obs_shapes), dict(options or {}))
