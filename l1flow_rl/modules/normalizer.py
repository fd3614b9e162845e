"""Per-dimension affine normalisers that live in a policy's state_dict.

"limits" maps [min, max] to [-1, 1]; a dimension whose range is below ``range_eps`` is only
shifted, so a constant value maps to 0 (Diffusion Policy's rule). "gaussian" maps to zero mean and
unit variance; a dimension with std below ``range_eps`` is only shifted. The default, before any
fit, is the identity, so data already in [-1, 1] needs no fit.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn

__all__ = ["ACTION_RANGE", "Normalizer", "NormalizerDict", "NormalizerMode", "clip_actions"]

NormalizerMode = Literal["identity", "limits", "gaussian"]
_MODES = ("identity", "limits", "gaussian")

#: the demonstrated action range in normalised units under the ``limits`` normaliser (the default for
#: actions): what the fine-tuning actors clip the chunks they execute and value to
ACTION_RANGE = (-1.0, 1.0)


def clip_actions(x: Tensor) -> Tensor:
    """Normalised actions clipped to :data:`ACTION_RANGE` (gradient zero outside it)."""
    return x.clamp(*ACTION_RANGE)


class Normalizer(nn.Module):
    """y = x * scale + offset over the trailing ``shape`` dims."""

    scale: Tensor
    offset: Tensor

    def __init__(self, shape: int | tuple[int, ...], range_eps: float = 1e-4) -> None:
        super().__init__()
        self.shape = (shape,) if isinstance(shape, int) else tuple(shape)
        self.range_eps = range_eps
        self.register_buffer("scale", torch.ones(self.shape))
        self.register_buffer("offset", torch.zeros(self.shape))
        # 0 identity, 1 limits, 2 gaussian; a buffer so the mode travels with the state_dict.
        self.register_buffer("mode_id", torch.zeros((), dtype=torch.long))

    @property
    def mode(self) -> NormalizerMode:
        return _MODES[int(self.mode_id)]  # type: ignore[return-value]

    @torch.no_grad()
    def fit(self, data: Tensor, mode: NormalizerMode = "limits", name: str = "data") -> Normalizer:
        """Fit from samples ``[..., *shape]``."""
        if mode not in _MODES:
            raise ValueError(f"normaliser mode for {name!r} must be one of {_MODES}, got {mode!r}")
        if tuple(data.shape[-len(self.shape) :]) != self.shape:
            raise ValueError(
                f"normaliser for {name!r} expects trailing shape {self.shape}, got {tuple(data.shape)}"
            )
        flat = data.reshape(-1, *self.shape).double()
        if flat.shape[0] == 0:
            raise ValueError(f"cannot fit the normaliser for {name!r} on zero samples")
        if not torch.isfinite(flat).all():
            raise ValueError(f"cannot fit the normaliser for {name!r}: the data contain NaN or Inf")
        if mode == "limits":
            lo, hi = flat.min(0).values, flat.max(0).values
            return self.set_limits(lo, hi)
        if mode == "gaussian":
            return self.set_gaussian(flat.mean(0), flat.std(0, correction=0))
        self.scale.fill_(1.0)
        self.offset.zero_()
        self.mode_id.fill_(0)
        return self

    @torch.no_grad()
    def set_limits(self, low: Tensor, high: Tensor) -> Normalizer:
        low, high = torch.as_tensor(low).double(), torch.as_tensor(high).double()
        span = high - low
        degenerate = span < self.range_eps
        scale = torch.where(degenerate, torch.ones_like(span), 2.0 / span)
        offset = torch.where(degenerate, -low, -1.0 - low * scale)
        self.scale.copy_(scale)
        self.offset.copy_(offset)
        self.mode_id.fill_(1)
        return self

    @torch.no_grad()
    def set_gaussian(self, mean: Tensor, std: Tensor) -> Normalizer:
        mean, std = torch.as_tensor(mean).double(), torch.as_tensor(std).double()
        degenerate = std < self.range_eps
        scale = torch.where(degenerate, torch.ones_like(std), 1.0 / std)
        self.scale.copy_(scale)
        self.offset.copy_(-mean * scale)
        self.mode_id.fill_(2)
        return self

    def normalize(self, x: Tensor) -> Tensor:
        return x * self.scale + self.offset

    def unnormalize(self, y: Tensor) -> Tensor:
        return (y - self.offset) / self.scale

    def extra_repr(self) -> str:
        return f"shape={self.shape}"


class NormalizerDict(nn.ModuleDict):
    """One :class:`Normalizer` per observation entry; entries without one pass through."""

    def __init__(self, shapes: Mapping[str, tuple[int, ...]] | None = None) -> None:
        super().__init__({k: Normalizer(v) for k, v in (shapes or {}).items()})

    def normalize(self, obs: TensorDictBase) -> TensorDictBase:
        out = obs.copy()
        for key, norm in self.items():
            out.set(key, norm.normalize(obs.get(key)))
        return out

    def fit(self, data: Mapping[str, Tensor] | TensorDict, mode: NormalizerMode = "limits") -> NormalizerDict:
        for key, norm in self.items():
            if key not in data:
                raise KeyError(
                    f"cannot fit the observation normaliser: entry {key!r} is missing from the data"
                )
            norm.fit(data[key], mode, name=key)
        return self
