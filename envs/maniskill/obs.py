"""ManiSkill's nested observation dict -> the project's flat entries ("state", "rgb").

Used both on live observations (leading dim = parallel envs) and on recorded demonstrations
(leading dim = time), so any number of leading dims is accepted.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["STATE_GROUPS", "flatten_maniskill_obs"]

#: The groups that make up the flat state, in this order (ManiSkill's FlattenRGBDObservationWrapper
#: flattens what is left after removing the sensors: ``agent`` then ``extra``).
STATE_GROUPS = ("agent", "extra")


def _as_tensor(value: Any, name: str) -> Tensor:
    if isinstance(value, Tensor):
        return value
    if isinstance(value, (np.ndarray, np.generic, bool, int, float)):
        return torch.as_tensor(np.asarray(value))
    raise TypeError(f"observation entry {name!r}: expected a tensor or array, got {type(value).__name__}")


def _leaves(group: Mapping[str, Any], prefix: str) -> list[tuple[str, Tensor]]:
    out = []
    for key, value in group.items():
        name = f"{prefix}/{key}"
        if isinstance(value, Mapping):
            out += _leaves(value, name)
        else:
            out.append((name, _as_tensor(value, name)))
    return out


def _camera_rgb(obs: Mapping[str, Any], camera: str | None) -> Tensor:
    sensors = obs["sensor_data"]
    if camera is None:
        if len(sensors) != 1:
            raise ValueError(
                f"observation has cameras {sorted(sensors)}; pass camera=<name> to pick the one to use"
            )
        camera = next(iter(sensors))
    if camera not in sensors:
        raise KeyError(f"camera {camera!r} not in observation['sensor_data'] (has {sorted(sensors)})")
    if "rgb" not in sensors[camera]:
        raise KeyError(
            f"observation['sensor_data'][{camera!r}] has no 'rgb' (has {sorted(sensors[camera])}); "
            "make the env with obs_mode='rgb'"
        )
    rgb = _as_tensor(sensors[camera]["rgb"], f"sensor_data/{camera}/rgb")
    if rgb.ndim < 3 or rgb.shape[-1] != 3:
        raise ValueError(f"sensor_data/{camera}/rgb: expected [..., H, W, 3], got {tuple(rgb.shape)}")
    if rgb.dtype != torch.uint8:
        raise TypeError(f"sensor_data/{camera}/rgb: expected uint8, got {rgb.dtype}")
    return rgb.movedim(-1, -3)  # ManiSkill is channels-last; the encoders read [..., 3, H, W]


def flatten_maniskill_obs(obs: Mapping[str, Any], camera: str | None = None) -> dict[str, Tensor]:
    """Flatten a ManiSkill observation dict (``obs_mode`` rgb, or state_dict) into project entries.

    Returns ``{"state": float32 [..., D]}`` — every leaf of ``agent`` then ``extra``, in key order,
    each flattened past the leading dims (a per-env scalar such as ``is_grasped`` becomes one
    column) — plus ``"rgb": uint8 [..., 3, H, W]`` when the observation has camera data. Leaves may
    be torch tensors or numpy arrays (as read from a demo file); the leading dims (parallel envs,
    or time) are taken from ``agent/qpos``-style leaves and must agree across entries.

    Example:
        >>> import torch
        >>> obs = {"agent": {"qpos": torch.zeros(4, 9), "qvel": torch.zeros(4, 9)},
        ...        "extra": {"is_grasped": torch.zeros(4, dtype=torch.bool), "tcp_pose": torch.zeros(4, 7)},
        ...        "sensor_data": {"base_camera": {"rgb": torch.zeros(4, 8, 8, 3, dtype=torch.uint8)}}}
        >>> {k: tuple(v.shape) for k, v in flatten_maniskill_obs(obs).items()}
        {'state': (4, 26), 'rgb': (4, 3, 8, 8)}
    """
    missing = [g for g in STATE_GROUPS if g not in obs]
    if missing:
        raise KeyError(
            f"ManiSkill observation lacks {missing} (has {sorted(obs)}); expected obs_mode 'rgb' or "
            "'state_dict', not the already-flat 'state'"
        )
    leaves = _leaves(obs["agent"], "agent") + _leaves(obs["extra"], "extra")
    out: dict[str, Tensor] = {}
    if "sensor_data" in obs and len(obs["sensor_data"]) > 0:
        out["rgb"] = _camera_rgb(obs, camera)
        batch = out["rgb"].shape[:-3]
    else:
        # qpos is always there and always [..., dof]: it fixes the leading dims.
        batch = _as_tensor(obs["agent"]["qpos"], "agent/qpos").shape[:-1]
    columns = []
    for name, value in leaves:
        if value.shape[: len(batch)] != batch:
            raise ValueError(
                f"observation entry {name!r} has shape {tuple(value.shape)}; "
                f"expected leading dims {tuple(batch)}"
            )
        columns.append(value.reshape(*batch, -1).to(torch.float32))
    state = torch.cat(columns, dim=-1)
    return {"state": state, **out}
