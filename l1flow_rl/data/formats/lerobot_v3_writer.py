"""Writing episodes (the layout of :mod:`l1flow_rl.data.episodes`) as a LeRobot v3.0 data set folder.

What goes where::

    meta/info.json            codebase_version "v3.0", fps, features (dtype, shape, names), path templates
    meta/stats.json           min, max, mean, std, count, q01..q99 per feature (images per channel in [0, 1])
    meta/tasks.parquet        the task string(s), indexed by task as LeRobot reads it back
    meta/episodes/chunk-000/file-000.parquet
                              per episode: index, length, tasks, its rows in the data file
                              (dataset_from_index, dataset_to_index), its window in each video
    data/chunk-000/file-000.parquet
                              one row per step: the features below plus timestamp, frame_index,
                              episode_index, index, task_index
    videos/observation.images.<camera>/chunk-000/file-000.mp4
    meta/l1flow_rl.json       what LeRobot has no field for: env id, control mode and control kind

Episode keys -> features: a tensor observation -> ``observation.state``; a TensorDict observation's
flat entry ``k`` -> ``observation.state`` for ``state``, else ``observation.k``; an image entry ``k``
-> ``observation.images.k``; ``action``; ``("next", "reward")`` -> ``next.reward``; ``("next",
"done")`` and ``("next", "terminated")`` -> ``next.done``, ``next.terminated``; any other ``("next",
k)`` step flag or value (``success``, ...) -> ``next.k``. ``("next", "truncated")`` is not stored (it is
``done and not terminated``), nor is ``("next", "observation")``, which is the next row's observation
inside an episode: LeRobot has no place for the observation after an episode's last action, so that
one is lost, and the reader says ``has_final_observation=False``.

Cameras are stored as H.264 mp4 (``cameras="video"``, LeRobot's usual storage; lossy: yuv420p colour
and compression change pixel values by a few levels) or as PNG images in the data parquet
(``cameras="image"``, LeRobot's ``image`` dtype; exact). Everything goes into one file of each kind:
LeRobot's size limits per file only decide when its recorder starts a new file; its reader takes
files of any size.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from l1flow_rl.data.episodes import EpisodeDataError
from l1flow_rl.data.formats.video import VideoWriter
from l1flow_rl.data.metadata import episodes_metadata, strip_metadata

__all__ = ["write_lerobot_v3"]

CODEBASE_VERSION = "v3.0"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
LOCAL_METADATA = "meta/l1flow_rl.json"
_QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
_NOT_STORED = {"observation", "truncated"}


def _pa():
    try:
        # the lerobot extra: parquet tables
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as err:
        raise ImportError(
            "LeRobot v3 data sets need pyarrow, which is not installed: pip install 'l1flow-rl[lerobot]'"
        ) from err
    return pa, pq


def _columns(steps: TensorDictBase) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(numeric feature name -> [N, ...] array, camera feature name -> uint8 [N, H, W, 3])."""
    numeric: dict[str, np.ndarray] = {}
    cameras: dict[str, np.ndarray] = {}
    obs = steps.get("observation")
    entries = {"state": obs} if isinstance(obs, torch.Tensor) else dict(obs.items())
    for name, value in entries.items():
        if value.dim() == 4:
            if value.dtype != torch.uint8 or value.shape[1] != 3:
                raise EpisodeDataError(
                    f"observation entry {name!r}: images must be uint8 [N, 3, H, W], got {value.dtype} "
                    f"{list(value.shape)}"
                )
            cameras[f"observation.images.{name}"] = value.permute(0, 2, 3, 1).contiguous().numpy()
        elif value.dim() == 2:
            numeric["observation.state" if name == "state" else f"observation.{name}"] = value.float().numpy()
        else:
            raise EpisodeDataError(
                f"observation entry {name!r}: expected [N, D] or uint8 images [N, 3, H, W], got "
                f"{list(value.shape)}"
            )
    numeric["action"] = steps.get("action").float().numpy()
    for key in steps.get("next").keys():  # noqa: SIM118 (a TensorDict's keys, not a dict's)
        if key in _NOT_STORED:
            continue
        value = steps.get(("next", key))
        if (
            not isinstance(value, torch.Tensor)
            or value.dim() > 2
            or (value.dim() == 2 and value.shape[1] != 1)
        ):
            raise EpisodeDataError(
                f"('next', {key!r}): only per-step values [N] or [N, 1] can be stored as next.{key}, "
                f"got {type(value).__name__} {list(getattr(value, 'shape', []))}"
            )
        value = value.reshape(-1, 1)
        numeric[f"next.{key}"] = value.numpy() if value.dtype == torch.bool else value.float().numpy()
    return numeric, cameras


def _stats(values: np.ndarray, image: bool) -> dict[str, Any]:
    """LeRobot's statistics: per dimension, or per channel over [0, 1] as [3, 1, 1] for images."""
    if image:
        x = values.astype(np.float64).transpose(0, 3, 1, 2) / 255.0  # [N, 3, H, W]
        x = x.transpose(1, 0, 2, 3).reshape(3, -1).T  # [N*H*W, 3]
        shape: tuple[int, ...] = (3, 1, 1)
    else:
        x = values.astype(np.float64).reshape(values.shape[0], -1)
        shape = x.shape[1:]
    stats = {
        "min": x.min(0),
        "max": x.max(0),
        "mean": x.mean(0),
        "std": x.std(0),
        **{name: np.quantile(x, q, axis=0) for name, q in _QUANTILES.items()},
    }
    out: dict[str, Any] = {k: v.reshape(shape).tolist() for k, v in stats.items()}
    out["count"] = [int(values.shape[0])]
    return out


def _arrow_column(pa, values: np.ndarray):
    """A scalar column for shape (1,), a fixed-size list column for (D,) (LeRobot's Sequence(length=D))."""
    if values.shape[1:] == (1,):
        return pa.array(values.reshape(-1))
    flat = pa.array(values.reshape(-1))
    return pa.FixedSizeListArray.from_arrays(flat, int(np.prod(values.shape[1:])))


def _dtype_name(values: np.ndarray) -> str:
    return "bool" if values.dtype == np.bool_ else str(values.dtype)


def _png_column(pa, frames: np.ndarray):
    """LeRobot's ``image`` feature: a struct of PNG bytes and a path (None: the bytes are the image)."""
    # the app extra: PNG-encoded image columns
    import imageio.v3 as iio

    encoded = [iio.imwrite("<bytes>", frame, extension=".png") for frame in frames]
    return pa.StructArray.from_arrays(
        [pa.array(encoded, type=pa.binary()), pa.array([None] * len(encoded), type=pa.string())],
        names=["bytes", "path"],
    )


def _tasks_table(pa, tasks: Sequence[str]):
    """tasks.parquet as pandas writes a frame indexed by ``task``, so that LeRobot's
    ``pd.read_parquet`` restores that index (written without pandas, which is no dependency here)."""
    pandas_meta = {
        "index_columns": ["task"],
        "column_indexes": [
            {
                "name": None,
                "field_name": None,
                "pandas_type": "unicode",
                "numpy_type": "object",
                "metadata": None,
            }
        ],
        "columns": [
            {
                "name": "task_index",
                "field_name": "task_index",
                "pandas_type": "int64",
                "numpy_type": "int64",
                "metadata": None,
            },
            {
                "name": "task",
                "field_name": "task",
                "pandas_type": "unicode",
                "numpy_type": "object",
                "metadata": None,
            },
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.0",
    }
    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()), "task": pa.array(list(tasks))})
    return table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode()})


def write_lerobot_v3(
    episodes: TensorDictBase,
    root: str | os.PathLike,
    *,
    fps: int,
    task: str | None = None,
    robot_type: str | None = None,
    cameras: str = "video",
) -> Path:
    """Write ``episodes`` as a LeRobot v3.0 folder at ``root`` (see the module docstring); returns it.

    Args:
        episodes: steps in the layout of :mod:`l1flow_rl.data.episodes` (e.g. from ``load_episodes``),
            episodes stored contiguously; they are numbered 0, 1, ... in the order they appear.
        fps: the control frequency (LeRobot's timestamps are frame_index / fps).
        task: the task description of every episode (default: the episodes' env id, else "task").
        robot_type: LeRobot's ``robot_type`` field.
        cameras: ``"video"`` (H.264 mp4, lossy) or ``"image"`` (PNG in the parquet, exact).

    The folder appears under its final name only once complete; an existing ``root`` is refused.

    Example:
        >>> eps = load_episodes("demos/PushT.zarr")  # doctest: +SKIP
        >>> write_lerobot_v3(eps, "pusht_v3", fps=10, task="push the T into place")  # doctest: +SKIP
    """
    pa, pq = _pa()
    if cameras not in ("video", "image"):
        raise ValueError(f"cameras must be 'video' or 'image', got {cameras!r}")
    if int(fps) <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    root = Path(root)
    if root.exists():
        raise FileExistsError(f"{root}: exists; write the LeRobot data set to a new folder")
    steps, _ = strip_metadata(episodes)
    meta = episodes_metadata(episodes)
    ids, counts = torch.unique_consecutive(steps.get("episode").reshape(-1), return_counts=True)
    if ids.unique().numel() != ids.numel():
        raise EpisodeDataError(
            "episodes: an episode's steps are not contiguous; store each episode's steps together"
        )
    lengths = counts.tolist()
    n = int(sum(lengths))
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    episode_index = np.repeat(np.arange(len(lengths), dtype=np.int64), lengths)
    frame_index = np.arange(n, dtype=np.int64) - np.repeat(starts, lengths)
    task = task or meta.env_id or "task"
    numeric, camera_frames = _columns(steps)

    features: dict[str, dict[str, Any]] = {}
    columns: dict[str, Any] = {}
    stats: dict[str, Any] = {}
    for name, values in numeric.items():
        features[name] = {"dtype": _dtype_name(values), "shape": list(values.shape[1:]), "names": None}
        columns[name] = _arrow_column(pa, values)
        stats[name] = _stats(values.astype(np.float64), image=False)
    dtype = "video" if cameras == "video" else "image"
    for name, frames in camera_frames.items():
        h, w, c = frames.shape[1:]
        features[name] = {"dtype": dtype, "shape": [h, w, c], "names": ["height", "width", "channels"]}
        if cameras == "image":
            columns[name] = _png_column(pa, frames)
        stats[name] = _stats(frames, image=True)
    timestamp = (frame_index / float(fps)).astype(np.float32)
    defaults = {
        "timestamp": timestamp,
        "frame_index": frame_index,
        "episode_index": episode_index,
        "index": np.arange(n, dtype=np.int64),
        "task_index": np.zeros(n, dtype=np.int64),
    }
    for name, values in defaults.items():
        features[name] = {"dtype": str(values.dtype), "shape": [1], "names": None}
        columns[name] = pa.array(values)
        stats[name] = _stats(values.reshape(-1, 1).astype(np.float64), image=False)

    tmp = root.parent / f".{root.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        data_file = tmp / DATA_PATH.format(chunk_index=0, file_index=0)
        data_file.parent.mkdir(parents=True)
        pq.write_table(pa.table(columns), data_file, compression="snappy")
        episode_rows: dict[str, Any] = {
            "episode_index": pa.array(range(len(lengths)), pa.int64()),
            "tasks": pa.array([[task]] * len(lengths), pa.list_(pa.string())),
            "length": pa.array(lengths, pa.int64()),
            "data/chunk_index": pa.array([0] * len(lengths), pa.int64()),
            "data/file_index": pa.array([0] * len(lengths), pa.int64()),
            "dataset_from_index": pa.array(starts, pa.int64()),
            "dataset_to_index": pa.array(starts + np.asarray(lengths), pa.int64()),
        }
        if cameras == "video":
            for name, frames in camera_frames.items():
                h, w, _ = frames.shape[1:]
                video = VideoWriter(
                    tmp / VIDEO_PATH.format(video_key=name, chunk_index=0, file_index=0), fps, h, w
                )
                try:
                    video.write(frames)
                finally:
                    video.close()
                features[name]["info"] = {
                    "video.height": h,
                    "video.width": w,
                    "video.codec": "h264",
                    "video.pix_fmt": "yuv420p",
                    "video.is_depth_map": False,
                    "video.fps": int(fps),
                    "video.channels": 3,
                    "has_audio": False,
                }
                episode_rows[f"videos/{name}/chunk_index"] = pa.array([0] * len(lengths), pa.int64())
                episode_rows[f"videos/{name}/file_index"] = pa.array([0] * len(lengths), pa.int64())
                episode_rows[f"videos/{name}/from_timestamp"] = pa.array(starts / float(fps), pa.float64())
                ends = (starts + np.asarray(lengths)) / float(fps)
                episode_rows[f"videos/{name}/to_timestamp"] = pa.array(ends, pa.float64())
        episode_rows["meta/episodes/chunk_index"] = pa.array([0] * len(lengths), pa.int64())
        episode_rows["meta/episodes/file_index"] = pa.array([0] * len(lengths), pa.int64())
        episodes_file = tmp / EPISODES_PATH
        episodes_file.parent.mkdir(parents=True)
        pq.write_table(pa.table(episode_rows), episodes_file)
        pq.write_table(_tasks_table(pa, [task]), tmp / "meta" / "tasks.parquet")
        info = {
            "codebase_version": CODEBASE_VERSION,
            "robot_type": robot_type,
            "total_episodes": len(lengths),
            "total_frames": n,
            "total_tasks": 1,
            "chunks_size": 1000,
            "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 500,
            "fps": int(fps),
            "splits": {"train": f"0:{len(lengths)}"},
            "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if cameras == "video" and camera_frames else None,
            "features": features,
        }
        (tmp / "meta" / "info.json").write_text(json.dumps(info, indent=4))
        (tmp / "meta" / "stats.json").write_text(json.dumps(stats, indent=4))
        local = {k: getattr(meta, k) for k in ("env_id", "control_mode", "control")}
        local["source"] = meta.source
        (tmp / LOCAL_METADATA).write_text(json.dumps(local, indent=1))
        os.replace(tmp, root)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return root
