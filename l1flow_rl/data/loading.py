"""``load_episodes``: any supported demonstration file -> one flat TensorDict of steps.

Supported (detected from the content, not the name):

* ManiSkill ``.h5`` with its ``.json`` (options: ``control_mode`` to check, ``camera``);
* robomimic / robosuite ``.hdf5`` (``state_keys``, ``image_key``);
* Diffusion Policy zarr replay buffers, a ``.zarr`` directory (``state_keys``, ``image_key``, ``action_key``);
* a LeRobot dataset as TorchRL's ``LeRobotExperienceReplay`` stores it on disk (``camera``);
* a LeRobot v3.0 dataset folder (``meta/info.json``, parquet, mp4; ``cameras``), see
  :mod:`l1flow_rl.data.formats.lerobot_v3`.

With ``memmap_dir`` the episodes stream one at a time into a TorchRL ``LazyMemmapStorage`` under that
directory, so data larger than RAM loads; opening the same source again reuses the stored copy.

What the reader knows about the data (format, source, env id, control, whether rewards and final
observations were recorded) travels inside the episodes; read it with :func:`episodes_metadata`.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyMemmapStorage

from l1flow_rl.config.data import QUALITY_LABELS
from l1flow_rl.data.episodes import EpisodeDataError, where
from l1flow_rl.data.metadata import EpisodeMetadata, attach_metadata, episodes_metadata, strip_metadata
from l1flow_rl.data.publish import publish_dir

if TYPE_CHECKING:
    from l1flow_rl.data.formats.base import EpisodeFile

__all__ = ["dataset_problem", "episodes_metadata", "load_episodes", "open_episode_file"]

#: Written beside a memory-mapped copy: where it came from (for reuse checks and error messages).
SOURCE_FILE = "l1flow_source.json"
#: Version of the step layout in a stored copy; copies of an older layout are rebuilt.
LAYOUT_VERSION = 2


def _is_zarr(path: Path) -> bool:
    return (path / "zarr.json").is_file() or (path / ".zgroup").is_file()


def _reader_class(path: Path) -> type[EpisodeFile]:
    """The reader of ``path``'s format, told from its content; errors name the file and the formats."""
    # The readers import h5py, which only the app extra installs: imported when a file is opened, so
    # that a core install imports the data layer.
    try:
        import h5py

        from l1flow_rl.data.formats.base import open_h5
        from l1flow_rl.data.formats.dp_zarr import DiffusionPolicyZarr
        from l1flow_rl.data.formats.lerobot import LeRobotDirectory, is_raw_lerobot, is_torchrl_lerobot
        from l1flow_rl.data.formats.lerobot_v3 import LeRobotV3Directory
        from l1flow_rl.data.formats.maniskill import ManiSkillFile
        from l1flow_rl.data.formats.robomimic import RobomimicFile
    except ImportError as err:
        raise ImportError(
            f"{path}: reading demonstration files needs {err.name}, which is not installed: "
            "pip install 'l1flow-rl[app]'"
        ) from err
    if not path.exists():
        raise EpisodeDataError(f"{path}: no such file or directory")
    if path.is_dir():
        if is_torchrl_lerobot(path):
            return LeRobotDirectory
        if is_raw_lerobot(path):  # meta/info.json: LeRobot's own layout (v3.0; older ones refused)
            return LeRobotV3Directory
        if _is_zarr(path):
            return DiffusionPolicyZarr
        raise EpisodeDataError(
            f"{path}: a directory that is neither a zarr store nor a LeRobot dataset; supported: "
            "ManiSkill .h5+.json, robomimic .hdf5, Diffusion Policy .zarr, LeRobot v3.0 folder, LeRobot "
            "(TorchRL copy)"
        )
    if h5py.is_hdf5(path):
        with open_h5(path) as f:
            return RobomimicFile if "data" in f else ManiSkillFile
    raise EpisodeDataError(
        f"{path}: not a supported demonstration file (not HDF5; truncated?); supported: ManiSkill "
        ".h5+.json, robomimic .hdf5, Diffusion Policy .zarr directory, LeRobot directory (TorchRL copy)"
    )


def dataset_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` is no demonstration dataset this loader reads (its format is told as
    :func:`open_episode_file` tells it, nothing is loaded), or None; also None where the readers are
    not installed, which opening the file reports."""
    path = Path(path)
    try:
        _reader_class(path)
    except EpisodeDataError as err:
        return str(err).removeprefix(f"{path}: ")
    except ImportError:
        return None
    except OSError as err:  # HDF5's signature, but the file does not open (truncated, unreadable)
        return f"cannot be read: {err}"
    return None


def open_episode_file(path: str | os.PathLike, **options) -> EpisodeFile:
    """The reader for ``path``'s format, opened. Errors name the file and what was expected."""
    path = Path(path)
    reader = _reader_class(path)
    try:
        return reader(path, **options)
    except TypeError as err:
        raise TypeError(f"{path}: option not understood by the {reader.format_name} reader: {err}") from err


def _selected_ids(reader: EpisodeFile, labels: Sequence[str] | None) -> list[int]:
    """The reader's episode ids, only those whose quality label is in ``labels`` when given."""
    ids = reader.episode_ids()
    if labels is None:
        return ids
    unknown = [lb for lb in labels if lb not in QUALITY_LABELS]
    if unknown or not labels:
        raise ValueError(
            f"labels={list(labels)!r}: unknown label(s) {unknown}; expected a non-empty subset of "
            f"{list(QUALITY_LABELS)}"
        )
    found = reader.episode_labels()
    if found is None:
        raise EpisodeDataError(
            f"{reader.path}: records no quality labels, so labels={list(labels)!r} selects nothing; "
            "make a labelled set with demos.quality=mixed, or drop the labels filter"
        )
    kept = [e for e in ids if found[e] in labels]
    if not kept:
        counts = {lb: sum(v == lb for v in found.values()) for lb in sorted(set(found.values()))}
        raise EpisodeDataError(
            f"{reader.path}: no episode is labelled {list(labels)} (the file holds {counts})"
        )
    return kept


def _episode_lengths(reader: EpisodeFile, labels: Sequence[str] | None = None) -> tuple[list[int], list[int]]:
    ids = _selected_ids(reader, labels)
    if not ids:
        raise EpisodeDataError(f"{reader.path}: contains no episodes")
    lengths = [reader.episode_length(e) for e in ids]
    for e, n in zip(ids, lengths):
        if n < 1:
            raise EpisodeDataError(f"{where(reader.path, e, 'action')}: the episode has no steps")
    return ids, lengths


def _stack(reader: EpisodeFile, ids: list[int], parts: list[TensorDict]) -> TensorDict:
    try:
        return torch.cat(parts, 0)
    except (RuntimeError, KeyError, ValueError) as err:
        first = parts[0]
        for e, part in zip(ids, parts):
            if set(part.keys(True, True)) != set(first.keys(True, True)):
                raise EpisodeDataError(
                    f"{where(reader.path, e)}: entries {sorted(map(str, part.keys(True, True)))} differ "
                    f"from episode {ids[0]}'s {sorted(map(str, first.keys(True, True)))}"
                ) from err
        raise EpisodeDataError(f"{reader.path}: episodes do not share shapes: {err}") from err


def _fingerprint(path: Path, options: dict) -> dict:
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    if path.suffix == ".h5" and path.with_suffix(".json").is_file():
        files.append(path.with_suffix(".json"))
    return {
        "source": str(path.resolve()),
        "bytes": sum(p.stat().st_size for p in files),
        "mtime_ns": max(p.stat().st_mtime_ns for p in files),
        "options": {k: repr(v) for k, v in sorted(options.items())},
        "layout": LAYOUT_VERSION,
    }


def _load_memmap(
    reader: EpisodeFile, options: dict, target: Path, progress: bool, labels: Sequence[str] | None = None
) -> TensorDictBase:
    fingerprint = _fingerprint(reader.path, {**options, **({"labels": list(labels)} if labels else {})})
    marker = target / SOURCE_FILE
    if marker.is_file():
        stored = json.loads(marker.read_text())
        if {**stored["fingerprint"], "layout": LAYOUT_VERSION} == fingerprint and stored["fingerprint"].get(
            "layout"
        ) != LAYOUT_VERSION:
            shutil.rmtree(target)  # our own copy of this very source in an older step layout: rebuild
            return _load_memmap(reader, options, target, progress, labels)
        if stored["fingerprint"] != fingerprint:
            raise EpisodeDataError(
                f"{target}: holds a stored copy of {stored['fingerprint']['source']} (or of an older "
                f"version of it, or with other options), not of {reader.path} as now; use another "
                "memmap_dir or delete this one"
            )
        return TensorDict.load_memmap(target)
    if target.exists():
        raise EpisodeDataError(
            f"{target}: exists and is not a stored copy made by load_episodes; choose another memmap_dir"
        )
    ids, lengths = _episode_lengths(reader, labels)
    tmp = target.parent / f".{target.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.parent.mkdir(parents=True, exist_ok=True)
    storage = LazyMemmapStorage(sum(lengths), scratch_dir=tmp, existsok=True, auto_cleanup=False)
    row = 0
    episodes = zip(ids, lengths)
    if progress:
        # optional dependency (app extra): the progress bar
        from tqdm import tqdm

        episodes = tqdm(list(episodes), desc=f"storing {reader.path.name}", unit="episode")
    try:
        for e, n in episodes:
            part, _ = strip_metadata(reader.read_episode(e))  # kept once in the marker, not per row
            try:
                storage.set(range(row, row + n), part)
            except (RuntimeError, KeyError, ValueError) as err:
                raise EpisodeDataError(
                    f"{where(reader.path, e)}: entries or shapes differ from the first episode's: {err}"
                ) from err
            row += n
        storage.dumps(tmp)
        marker_tmp = tmp / SOURCE_FILE
        marker_tmp.write_text(json.dumps({"fingerprint": fingerprint, "metadata": reader.metadata}, indent=1))
        if not publish_dir(tmp, target):  # another process stored the same file first
            return _load_memmap(reader, options, target, progress, labels)  # checks its fingerprint
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return TensorDict.load_memmap(target)


def load_episodes(
    path: str | os.PathLike,
    *,
    memmap_dir: str | os.PathLike | None = None,
    progress: bool = False,
    labels: Sequence[str] | None = None,
    **options: Any,
) -> TensorDictBase:
    """Read every episode of a demonstration file into the layout of :mod:`l1flow_rl.data.episodes`.

    Args:
        path: a supported file or directory (see the module docstring).
        memmap_dir: store the steps memory-mapped under this directory (reused when the source is
            unchanged) instead of in RAM.
        progress: show a progress bar while storing.
        labels: keep only the episodes with these quality labels (a ``demos.quality=mixed`` file;
            see :data:`l1flow_rl.config.data.QUALITY_LABELS`); None keeps every episode.
        **options: for the format's reader, e.g. ``control_mode="pd_ee_delta_pos"`` for ManiSkill.

    Example:
        >>> eps = load_episodes("demos/PushCube-v1.h5", control_mode="pd_ee_delta_pos")  # doctest: +SKIP
        >>> eps["observation"].shape, eps["action"].shape, eps["next", "reward"].shape  # doctest: +SKIP
        (torch.Size([7000, 35]), torch.Size([7000, 4]), torch.Size([7000, 1]))
    """
    with open_episode_file(path, **options) as reader:
        meta = EpisodeMetadata.from_dict(reader.metadata)
        if memmap_dir is not None:
            data = _load_memmap(reader, options, Path(memmap_dir), progress, labels)
            extra = {**meta.extra, "memmap_dir": str(Path(memmap_dir).resolve())}
            return attach_metadata(data, EpisodeMetadata.from_dict({**meta.__dict__, "extra": extra}))
        ids, _ = _episode_lengths(reader, labels)
        return attach_metadata(_stack(reader, ids, [reader.read_episode(e) for e in ids]), meta)
