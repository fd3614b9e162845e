"""Writing robomimic ``.hdf5`` files, in the layout robomimic, MimicGen and Diffusion Policy read:

* ``data.attrs["env_args"]``: JSON with ``env_name``, ``env_version``, ``type`` (1: robosuite)
  and ``env_kwargs`` (the ``robosuite.make`` keyword arguments);
* ``data.attrs["total"]``: the number of samples (steps) in the file;
* ``data/demo_<i>``: ``states`` [T, S] (flattened MuJoCo states, the one before each action),
  ``actions`` [T, A], ``rewards`` [T], ``dones`` [T], ``obs/<key>`` [T, ...] and
  ``next_obs/<key>`` [T, ...]; attributes ``num_samples`` (T) and ``model_file`` (the MJCF XML);
* ``mask/<filter>``: demo names, robomimic's filter keys (optional).

The file appears under its final name only once it is complete (written beside it, then renamed).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

__all__ = ["RobomimicDemo", "RobomimicWriter"]

#: images are compressed (low-dimensional arrays are small, and gzip would slow readers)
_IMAGE_COMPRESSION = {"compression": "gzip", "compression_opts": 4}


class RobomimicDemo(dict):
    """One demonstration for :meth:`RobomimicWriter.add`: ``states``, ``actions``, ``rewards``,
    ``dones``, ``obs`` (key -> [T, ...]), optionally ``next_obs``, and ``model_file``."""


def _check(name: str, demo: Mapping[str, Any]) -> int:
    for key in ("states", "actions", "rewards", "dones", "model_file"):
        if key not in demo:
            raise ValueError(f"demo {name}: missing {key!r}")
    steps = len(demo["actions"])
    if steps < 1:
        raise ValueError(f"demo {name}: has no steps")
    arrays = {k: demo[k] for k in ("states", "rewards", "dones")}
    for group in ("obs", "next_obs"):
        arrays.update({f"{group}/{k}": v for k, v in (demo.get(group) or {}).items()})
    for key, value in arrays.items():
        if len(value) != steps:
            raise ValueError(f"demo {name}: {key!r} has {len(value)} steps, the actions {steps}")
        value = np.asarray(value)
        if value.dtype.kind == "f" and not np.isfinite(value).all():
            raise ValueError(f"demo {name}: {key!r} contains NaN or Inf")
    return steps


class RobomimicWriter:
    """Writes demonstrations one at a time into a robomimic file.

    Example:
        >>> with RobomimicWriter("lift.hdf5", env_args) as w:  # doctest: +SKIP
        ...     w.add(RobomimicDemo(states=s, actions=a, rewards=r, dones=d, obs={...}, model_file=xml))
    """

    def __init__(self, path: str | os.PathLike, env_args: Mapping[str, Any]) -> None:
        for key in ("env_name", "env_version", "env_kwargs"):
            if key not in env_args:
                raise ValueError(f"env_args needs {key!r} (robomimic's layout), got {sorted(env_args)}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(f".{self.path.name}.partial-{os.getpid()}")
        self._file = h5py.File(self._tmp, "w")
        self._data = self._file.create_group("data")
        self._data.attrs["env_args"] = json.dumps(env_args, default=_jsonable)
        self.num_demos = 0
        self._next_index = 0  # the next demo_<i> that add() names (past every copied episode's)
        self.total = 0

    def add(self, demo: Mapping[str, Any], name: str | None = None) -> str:
        """Append a demo (as ``demo_<n>`` unless ``name`` is given); returns its name."""
        name = name or f"demo_{self._next_index}"
        steps = _check(name, demo)
        group = self._data.create_group(name)
        group.create_dataset("states", data=np.asarray(demo["states"], dtype=np.float64))
        group.create_dataset("actions", data=np.asarray(demo["actions"], dtype=np.float64))
        group.create_dataset("rewards", data=np.asarray(demo["rewards"], dtype=np.float64))
        group.create_dataset("dones", data=np.asarray(demo["dones"], dtype=np.int64))
        for obs_group in ("obs", "next_obs"):
            values = demo.get(obs_group)
            if values:
                sub = group.create_group(obs_group)
                for key, value in values.items():
                    value = np.asarray(value)
                    options = _IMAGE_COMPRESSION if value.dtype == np.uint8 and value.ndim == 4 else {}
                    sub.create_dataset(key, data=value, **options)
        group.attrs["num_samples"] = steps
        group.attrs["model_file"] = demo["model_file"]
        for key, value in (demo.get("attrs") or {}).items():
            group.attrs[key] = value
        self.num_demos += 1
        self._next_index += 1
        self.total += steps
        return name

    def copy(self, group: h5py.Group) -> str:
        """Append an episode of another robomimic file verbatim under its own name (``demo_<i>``):
        every dataset and attribute it holds is kept, not only those :meth:`add` writes."""
        name = group.name.rsplit("/", 1)[1]
        if name in self._data:
            raise ValueError(f"demo {name}: already in {self.path}")
        group.file.copy(group, self._data, name=name)
        self.num_demos += 1
        self._next_index = max(self._next_index, int(name.rsplit("_", 1)[1]) + 1)
        self.total += len(group["actions"])
        return name

    def add_mask(self, name: str, demos: Sequence[str]) -> None:
        """robomimic's filter key ``mask/<name>`` (e.g. ``train``/``valid``)."""
        self._file.require_group("mask").create_dataset(name, data=np.array(demos, dtype="S"))

    def set_data_attr(self, name: str, value: str | int | float) -> None:
        """An attribute of the file's ``data`` group (e.g. how its episodes were made)."""
        if name in ("env_args", "total"):
            raise ValueError(f"data attribute {name!r} is the writer's own")
        self._data.attrs[name] = value

    def close(self) -> Path:
        """Finish the file and give it its final name."""
        if self._file is None:
            return self.path
        self._data.attrs["total"] = self.total
        self._file.close()
        self._file = None
        os.replace(self._tmp, self.path)
        return self.path

    def abort(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> RobomimicWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"env_args holds a {type(value).__name__}, which JSON cannot store: {value!r}")
