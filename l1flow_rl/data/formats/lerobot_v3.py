"""LeRobot v3.0 data sets read from a local folder with pyarrow (tables) and PyAV (camera videos).

The layout (LeRobot's ``CODEBASE_VERSION = "v3.0"``): ``meta/info.json`` (fps, features with dtype,
shape and names, path templates), ``meta/episodes/chunk-*/file-*.parquet`` (one row per episode: its
length, its rows ``[dataset_from_index, dataset_to_index)``, the data file holding them, and for each
camera video the file and the time window ``[from_timestamp, to_timestamp)`` in it),
``data/chunk-*/file-*.parquet`` (one row per frame, many episodes per file) and
``videos/<camera>/chunk-*/file-*.mp4``.

Features -> episode keys: ``action`` -> ``"action"``; ``observation.state`` -> the state; another
numeric ``observation.<name>`` (e.g. ``observation.environment_state``) -> entry ``<name>``; a camera
``observation.images.<name>`` (``video`` or ``image`` dtype) -> uint8 entry ``<name>`` [T, 3, H, W].
With the state alone the observation is a plain tensor [T, D], as other readers give it.
``next.reward`` -> the reward (else 0 and ``has_rewards=False``); the episode ended in a terminal
state when ``next.terminated`` (or, without it, ``next.done``) is set at its last frame; other
``next.<k>`` features (``next.success``, ...) -> ``("next", k)``. LeRobot stores no observation after
an episode's last action (``has_final_observation=False``). ``meta/l1flow_rl.json``, which this
project's writer adds, gives the env id and control; a foreign data set has neither, and the task
config decides the control.

A v2.x folder (one parquet and one mp4 per episode) is refused, naming its version: convert it with
LeRobot's ``convert_dataset_v21_to_v30`` first.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from l1flow_rl.data.episodes import EpisodeDataError, assemble_episode, check_finite, where
from l1flow_rl.data.formats.base import EpisodeFile
from l1flow_rl.data.formats.video import LEROBOT_TOLERANCE_S, decode_window

__all__ = ["LeRobotV3Directory", "is_lerobot_v3"]

_EPISODE_COLUMNS = ("episode_index", "length", "dataset_from_index", "dataset_to_index")
_CAMERA_DTYPES = ("video", "image")
_FLAGS = ("next.reward", "next.done", "next.terminated")


def is_lerobot_v3(path: Path) -> bool:
    """A folder with ``meta/info.json`` (any LeRobot version: the reader refuses the others by name)."""
    return path.is_dir() and (path / "meta" / "info.json").is_file()


def _pq():
    try:
        # the lerobot extra: parquet tables
        import pyarrow.parquet as pq
    except ImportError as err:
        raise ImportError(
            "LeRobot v3 data sets need pyarrow, which is not installed: pip install 'l1flow-rl[lerobot]'"
        ) from err
    return pq


def _read_info(path: Path) -> dict[str, Any]:
    info_path = path / "meta" / "info.json"
    try:
        info = json.loads(info_path.read_text())
    except json.JSONDecodeError as err:
        raise EpisodeDataError(f"{info_path}: not valid JSON ({err})") from err
    if "codebase_version" not in info:
        raise EpisodeDataError(
            f"{where(info_path, key='codebase_version')}: missing; this reader expects LeRobot v3.0"
        )
    version = str(info["codebase_version"])
    if not version.startswith("v3."):
        raise EpisodeDataError(
            f"{info_path}: a LeRobot {version} data set (codebase_version {version!r}); this reader expects "
            "v3.0 (one parquet and one video per camera for many episodes). Convert it with LeRobot's "
            "convert_dataset_v21_to_v30 script first"
        )
    for key in ("fps", "features"):
        if key not in info:
            raise EpisodeDataError(f"{where(info_path, key=key)}: missing")
    return info


def _column(table, key: str, shape: Sequence[int], source: Path) -> np.ndarray:
    """A numeric column as [rows, *shape]: scalars for shape (1,), (nested) lists otherwise."""
    # the lerobot extra: parquet tables
    import pyarrow as pa

    column = table.column(key).combine_chunks()
    rows = len(column)
    while (
        pa.types.is_list(column.type)
        or pa.types.is_large_list(column.type)
        or pa.types.is_fixed_size_list(column.type)
    ):
        column = column.flatten()
    values = column.to_numpy(zero_copy_only=False)
    size = int(np.prod(shape))
    if values.size != rows * size:
        per_row = values.size / max(rows, 1)
        raise EpisodeDataError(
            f"{where(source, key=key)}: meta/info.json gives shape {list(shape)} ({size} values a row), the "
            f"file holds {per_row:g} values a row"
        )
    return values.reshape(rows, *shape)


class LeRobotV3Directory(EpisodeFile):
    """Reader for a LeRobot v3.0 folder (see the module docstring).

    Args:
        path: the data set's root folder (the one holding ``meta/``, ``data/`` and ``videos/``).
        cameras: ``"auto"`` reads every camera feature, a list names the cameras to read (``<name>``
            of ``observation.images.<name>``), ``None`` makes a state-only observation.
        tolerance_s: how far a decoded video frame may lie from the time a row asks for (LeRobot's
            default).
    """

    format_name = "lerobot_v3"

    def __init__(
        self,
        path: Path,
        *,
        cameras: str | Sequence[str] | None = "auto",
        tolerance_s: float = LEROBOT_TOLERANCE_S,
    ) -> None:
        super().__init__(path)
        self.info = _read_info(path)
        self.features: dict[str, dict[str, Any]] = self.info["features"]
        self.fps = float(self.info["fps"])
        self.tolerance_s = tolerance_s
        for key in ("action", "episode_index", "frame_index"):
            if key not in self.features:
                raise EpisodeDataError(
                    f"{where(path / 'meta' / 'info.json', key=f'features.{key}')}: missing; the data set has "
                    f"features {sorted(self.features)}"
                )
        all_cameras = {
            k.removeprefix("observation.images."): k
            for k, f in self.features.items()
            if f.get("dtype") in _CAMERA_DTYPES and k.startswith("observation.images.")
        }
        if cameras == "auto":
            chosen = list(all_cameras)
        elif cameras is None:
            chosen = []
        else:
            chosen = [cameras] if isinstance(cameras, str) else list(cameras)
            unknown = [c for c in chosen if c not in all_cameras]
            if unknown:
                raise EpisodeDataError(
                    f"{path}: cameras {unknown} are not features of the data set; it has "
                    f"{sorted(all_cameras)}"
                )
        self.cameras = {name: all_cameras[name] for name in chosen}
        self.entries = {
            ("state" if k == "observation.state" else k.removeprefix("observation.")): k
            for k, f in self.features.items()
            if k.startswith("observation.") and f.get("dtype") not in _CAMERA_DTYPES
        }
        if not self.entries and not self.cameras:
            raise EpisodeDataError(
                f"{where(path / 'meta' / 'info.json', key='features.observation.state')}: missing, and no "
                f"other observation feature is there (features {sorted(self.features)})"
            )
        self.extras = {
            k.removeprefix("next."): k for k in self.features if k.startswith("next.") and k not in _FLAGS
        }
        self._episodes = self._read_episodes()
        self._table_key: tuple[int, int] | None = None
        self._table: dict[str, np.ndarray] = {}
        local = path / "meta" / "l1flow_rl.json"
        self.local = json.loads(local.read_text()) if local.is_file() else {}

    # -- the episode table ---------------------------------------------------------------------
    def _read_episodes(self) -> dict[int, dict[str, Any]]:
        pq = _pq()
        folder = self.path / "meta" / "episodes"
        files = sorted(folder.glob("chunk-*/file-*.parquet"))
        if not files:
            raise EpisodeDataError(f"{folder}: no chunk-*/file-*.parquet; the episode table is missing")
        rows: list[dict[str, Any]] = []
        for file in files:
            table = pq.read_table(file)
            needed = [*_EPISODE_COLUMNS, "data/chunk_index", "data/file_index"]
            needed += [
                f"videos/{k}/{c}" for k in self.cameras.values() if self._is_video(k) for c in _VIDEO_COLUMNS
            ]
            missing = [c for c in needed if c not in table.column_names]
            if missing:
                raise EpisodeDataError(f"{where(file, key=missing[0])}: missing (columns missing: {missing})")
            rows += table.select(needed).to_pylist()
        rows.sort(key=lambda r: r["episode_index"])
        index = [int(r["episode_index"]) for r in rows]
        expected = list(range(len(index)))
        if index != expected:
            duplicated = sorted({i for i in index if index.count(i) > 1})
            absent = sorted(set(expected) - set(index))
            problem = f"repeated {duplicated}" if duplicated else f"missing {absent[:10]}"
            raise EpisodeDataError(
                f"{where(folder, key='episode_index')}: episode indices must run 0..{len(index) - 1} without "
                f"gaps; {problem} (found {index[:10]}{'...' if len(index) > 10 else ''})"
            )
        for r in rows:
            span = int(r["dataset_to_index"]) - int(r["dataset_from_index"])
            if span != int(r["length"]) or span < 1:
                raise EpisodeDataError(
                    f"{where(folder, r['episode_index'], 'length')}: length {r['length']} but rows "
                    f"[{r['dataset_from_index']}, {r['dataset_to_index']})"
                )
        return {int(r["episode_index"]): r for r in rows}

    def _is_video(self, feature: str) -> bool:
        return self.features[feature].get("dtype") == "video"

    def _numeric(self) -> dict[str, tuple[int, ...]]:
        keys = ["action", *self.entries.values(), *(k for k in _FLAGS if k in self.features)]
        keys += list(self.extras.values())
        return {k: tuple(self.features[k]["shape"]) for k in keys}

    def _data(self, row: dict[str, Any]) -> dict[str, np.ndarray]:
        """The columns of the data file holding ``row``'s episode (one file kept at a time)."""
        key = (int(row["data/chunk_index"]), int(row["data/file_index"]))
        if key != self._table_key:
            pq = _pq()
            template = self.info.get(
                "data_path", "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
            )
            file = self.path / template.format(chunk_index=key[0], file_index=key[1])
            if not file.is_file():
                raise EpisodeDataError(f"{file}: missing (the data of episode {row['episode_index']})")
            table = pq.read_table(file)
            images = [k for k in self.cameras.values() if not self._is_video(k)]
            wanted = {**self._numeric(), "episode_index": (1,), "frame_index": (1,)}
            if any(self._is_video(k) for k in self.cameras.values()):
                wanted["timestamp"] = (1,)
            missing = [k for k in [*wanted, *images] if k not in table.column_names]
            if missing:
                raise EpisodeDataError(
                    f"{where(file, key=missing[0])}: a feature of meta/info.json that the file lacks "
                    f"(missing: {missing})"
                )
            self._table = {k: _column(table, k, shape, file) for k, shape in wanted.items()}
            for k in images:
                self._table[k] = np.asarray(
                    table.column(k).combine_chunks().field("bytes").to_pylist(), object
                )
            self._table["_file"] = np.asarray(str(file))
            self._table_key = key
        return self._table

    # -- EpisodeFile -----------------------------------------------------------------------------
    @property
    def metadata(self) -> dict:
        control = {k: self.local[k] for k in ("env_id", "control_mode", "control") if self.local.get(k)}
        return {
            **super().metadata,
            **control,
            "has_rewards": "next.reward" in self.features,
            "has_final_observation": False,  # LeRobot keeps no observation after the last action
            "fps": self.fps,
            "robot_type": self.info.get("robot_type"),
            "codebase_version": self.info.get("codebase_version"),
        }

    def episode_ids(self) -> list[int]:
        return list(self._episodes)

    def episode_length(self, episode: int) -> int:
        return int(self._episodes[episode]["length"])

    def read_episode(self, episode: int) -> TensorDict:
        row = self._episodes[episode]
        data = self._data(row)
        source = Path(str(data["_file"]))
        rows = np.flatnonzero(data["episode_index"].reshape(-1) == episode)
        steps = int(row["length"])
        if rows.size != steps:
            raise EpisodeDataError(
                f"{where(source, episode, 'episode_index')}: {rows.size} rows, the episode table says {steps}"
            )
        frames = data["frame_index"].reshape(-1)[rows]
        order = np.argsort(frames, kind="stable")
        rows, frames = rows[order], frames[order]
        if not np.array_equal(frames, np.arange(steps)):
            raise EpisodeDataError(f"{where(source, episode, 'frame_index')}: not 0..{steps - 1}")

        def tensor(key: str) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(data[key][rows]))

        action = check_finite(tensor("action").float().reshape(steps, -1), source, episode, "action")
        entries: dict[str, torch.Tensor] = {}
        for name, key in self.entries.items():
            entries[name] = check_finite(tensor(key).float().reshape(steps, -1), source, episode, key)
        for name, key in self.cameras.items():
            entries[name] = self._camera(key, row, data, rows, source, episode)
        observation: torch.Tensor | dict = entries
        if list(entries) == ["state"]:
            observation = entries["state"]
        reward = None
        if "next.reward" in self.features:
            reward = check_finite(
                tensor("next.reward").float().reshape(steps), source, episode, "next.reward"
            )
        terminated = False
        for key in ("next.done", "next.terminated"):
            if key in self.features:
                flags = tensor(key).reshape(steps).bool()
                if flags[:-1].any():
                    step = int(flags[:-1].nonzero()[0])
                    raise EpisodeDataError(
                        f"{where(source, episode, key)}: set at frame {step}, before the episode's last "
                        f"frame {steps - 1}; an episode must end where {key} is set"
                    )
                if key == "next.terminated" or "next.terminated" not in self.features:
                    terminated = bool(flags[-1])
        extras = {}
        for name, key in self.extras.items():
            value = tensor(key).reshape(steps)
            extras[name] = (
                value if value.dtype == torch.bool else check_finite(value.float(), source, episode, key)
            )
        return assemble_episode(
            episode, observation, action, reward=reward, terminated=terminated, next_extra=extras
        )

    def _camera(
        self,
        key: str,
        row: dict[str, Any],
        data: dict[str, np.ndarray],
        rows: np.ndarray,
        source: Path,
        episode: int,
    ) -> torch.Tensor:
        """uint8 [T, 3, H, W] of one camera: decoded from its video window, or from PNG image cells."""
        shape = tuple(self.features[key]["shape"])
        if self._is_video(key):
            template = self.info.get("video_path") or ""
            if not template:
                raise EpisodeDataError(
                    f"{where(self.path / 'meta' / 'info.json', key='video_path')}: missing"
                )
            video = self.path / template.format(
                video_key=key,
                chunk_index=int(row[f"videos/{key}/chunk_index"]),
                file_index=int(row[f"videos/{key}/file_index"]),
            )
            times = float(row[f"videos/{key}/from_timestamp"]) + data["timestamp"].reshape(-1)[rows].astype(
                np.float64
            )
            frames = decode_window(video, times, tolerance_s=self.tolerance_s, key=key)
        else:
            # the app extra: PNG-encoded image columns
            import imageio.v3 as iio

            try:
                frames = np.stack([iio.imread(cell) for cell in data[key][rows]])
            except (OSError, ValueError, TypeError) as err:
                raise EpisodeDataError(
                    f"{where(source, episode, key)}: an image cannot be decoded ({err})"
                ) from err
        hwc = shape if shape[-1] in (1, 3, 4) else (shape[1], shape[2], shape[0])  # LeRobot gives [H, W, C]
        if frames.shape[1:] != tuple(hwc) or frames.shape[-1] != 3:
            raise EpisodeDataError(
                f"{where(source, episode, key)}: frames of shape {list(frames.shape[1:])}, meta/info.json "
                f"says {list(shape)} (RGB [height, width, 3] expected)"
            )
        return torch.from_numpy(frames).permute(0, 3, 1, 2).contiguous()


_VIDEO_COLUMNS = ("chunk_index", "file_index", "from_timestamp")
