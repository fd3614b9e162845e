"""Reading an observation history the way every network of the library takes it: the policy, and
the critics that score its chunks, accept the same inputs and refuse the same mistakes.

An observation is a tensor (a single flat entry, named :data:`STATE_KEY`) or a TensorDict of named
entries, each with batch dims ``[*B, To, ...]``; flat entries are ``[D]`` per step, images
``[3, H, W]`` uint8 per step (images travel as bytes; the encoder makes floats on the network's own
device).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from l1flow_rl.utils.value_checks import value_checks_enabled

__all__ = ["STATE_KEY", "read_observations"]

#: A plain tensor observation is treated as this single entry.
STATE_KEY = "state"


def _entries(
    observation: Tensor | TensorDictBase, obs_shapes: Mapping[str, tuple[int, ...]], key: str
) -> dict[str, Tensor]:
    if isinstance(observation, Tensor):
        if set(obs_shapes) != {STATE_KEY}:
            raise TypeError(f"{key!r} is a tensor, but the encoder expects entries {sorted(obs_shapes)}")
        return {STATE_KEY: observation}
    if not isinstance(observation, TensorDictBase):
        raise TypeError(f"{key!r} must be a Tensor or a TensorDict, got {type(observation).__name__}")
    entries = {}
    for k in obs_shapes:
        if k not in observation:
            raise KeyError(
                f"observation entry {(key, k)!r} is missing; the encoder expects {sorted(obs_shapes)}"
            )
        entries[k] = observation.get(k)
    return entries


def read_observations(
    observation: Tensor | TensorDictBase,
    obs_shapes: Mapping[str, tuple[int, ...]],
    obs_horizon: int,
    dtype: torch.dtype,
    *,
    key: str = "observation",
) -> tuple[TensorDict, tuple[int, ...]]:
    """Check an observation against the encoder's entries and return it flattened to batch
    ``[N, To]``, with its batch dims ``[*B]`` (``N = prod(B)``).

    Checked: every entry of ``obs_shapes`` is there (a tensor only for a single :data:`STATE_KEY`
    entry), each has shape ``[*B, obs_horizon, *entry shape]`` with the same ``B``, image entries
    (``[3, H, W]``) are uint8, and floating entries are finite (a value check, skipped inside
    :func:`~l1flow_rl.utils.value_checks.skip_value_checks`). Floating entries are cast to ``dtype`` (the
    network's: float64 data would clash with float32 weights); images stay uint8. Errors name the
    entry as ``key.entry``.

    Example:
        >>> obs, batch = read_observations(torch.zeros(4, 3, 2, 5), {"state": (5,)}, 2, torch.float32)
        >>> obs.batch_size, batch
        (torch.Size([12, 2]), (4, 3))
    """
    entries = _entries(observation, obs_shapes, key)
    batch: tuple[int, ...] | None = None
    for k, v in entries.items():
        shape = tuple(obs_shapes[k])
        name = key if isinstance(observation, Tensor) else f"{key}.{k}"
        nd = len(shape) + 1
        if v.dim() < nd or tuple(v.shape[-nd:]) != (obs_horizon, *shape):
            raise ValueError(
                f"{name!r} must have shape [*B, {obs_horizon}, {', '.join(map(str, shape))}] "
                f"(obs_horizon, entry shape), got {tuple(v.shape)}"
            )
        if len(shape) == 3 and v.dtype != torch.uint8:
            raise TypeError(f"{name!r} is an image entry [3, H, W] and must be uint8, got {v.dtype}")
        b = tuple(v.shape[:-nd])
        if batch is not None and b != batch:
            raise ValueError(f"{name!r} has batch dims {b}, other observation entries have {batch}")
        batch = b
        if v.is_floating_point():
            if value_checks_enabled() and not torch.isfinite(v).all():
                raise ValueError(f"{name!r} contains NaN or Inf")
            entries[k] = v.to(dtype)
    if batch is None:
        raise ValueError("the encoder expects no observation entries; there is nothing to read")
    n = math.prod(batch)
    flat = {k: v.reshape(n, obs_horizon, *obs_shapes[k]) for k, v in entries.items()}
    return TensorDict(flat, batch_size=[n, obs_horizon]), batch
