"""A user's robomimic or MimicGen file as a robosuite task's training data: the reader options that
select the task's observation, and, when the file lacks those observations (robomimic's
states-only layout, or other cameras), a copy with them regenerated from the stored states."""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from l1flow_rl.envs.robosuite.sim import image_key

from l1flow_rl.config import TaskConfig

__all__ = ["prepare_robomimic_dataset", "robosuite_reader_options"]


def robosuite_reader_options(task: TaskConfig) -> Mapping[str, Any]:
    """``state_keys`` and, for image tasks, the cameras' robomimic keys as named entries (the
    env's observation layout); state tasks read no image."""
    options: dict[str, Any] = {"state_keys": list(task.state_keys)}
    if task.obs_mode == "rgb":
        options["cameras"] = [image_key(c) for c in task.cameras]
    else:
        options["image_key"] = None
    return options


def _cache_name(path: Path, task: TaskConfig) -> str:
    stat = path.stat()
    views = "+".join(task.cameras) + f"{task.image_size}" if task.obs_mode == "rgb" else "state"
    key = f"{path.resolve()}|{stat.st_size}|{stat.st_mtime_ns}|{views}"
    return f"{path.stem}.{views}.{hashlib.sha1(key.encode()).hexdigest()[:10]}.hdf5"


def prepare_robomimic_dataset(
    task: TaskConfig, path: Path, data_dir: Path, *, workers: int | None = None
) -> Path:
    """``path`` itself when it stores the task's observations (its ``state_keys`` and, for image
    tasks, its cameras), else a copy under ``data_dir/robosuite/imported`` with robomimic's
    observations regenerated from the states (made once, reused while the source is unchanged)."""
    # optional dependency: h5py (robomimic files are HDF5; the formats import it)
    import h5py

    from l1flow_rl.data.formats.robomimic import has_observations

    path = Path(path)
    if not path.is_file() or not h5py.is_hdf5(path):
        return path  # not a robomimic file: the reader names the problem
    with h5py.File(path, "r") as h5:
        if "data" not in h5:
            return path
    cameras = list(task.cameras) if task.obs_mode == "rgb" else []
    if has_observations(path, [*task.state_keys, *(image_key(c) for c in cameras)]):
        return path
    target = Path(data_dir) / "robosuite" / "imported" / _cache_name(path, task)
    if target.is_file():
        return target
    # optional dependency: the module imports h5py
    from l1flow_rl.envs.robosuite.regenerate import regenerate_observations

    return regenerate_observations(path, target, cameras=cameras, image_size=task.image_size, workers=workers)
