"""Evaluation videos: frames of the filmed episodes, written as mp4 into the run directory and
handed to a TorchRL logger through its video API (``Logger.log_video``)."""

from __future__ import annotations

import importlib.util
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from l1flow_rl.envs.per_env import render_frames

__all__ = ["add_frames", "default_video_episodes", "log_videos", "video_episodes_to_film", "write_video"]

VIDEO_WRITER_HINT = "mp4 videos need imageio's ffmpeg backend: pip install imageio-ffmpeg (in l1flow-rl[app])"


def _has_mp4_writer() -> bool:
    return importlib.util.find_spec("imageio_ffmpeg") is not None


def default_video_episodes(device: str | torch.device) -> int:
    """Episodes filmed when ``eval.video_episodes`` is not set: one on a GPU, none on the CPU, where
    the first rendered frame costs seconds (the renderer starts) and every frame slows the episode."""
    return 1 if torch.device(device).type == "cuda" else 0


def video_episodes_to_film(configured: int | None, device: str | torch.device) -> int:
    """``eval.video_episodes``, or its device default when unset, checked before any episode runs:
    without imageio's ffmpeg backend imageio would pick another writer for the .mp4 and fail only
    when the first video is written, after the training. Asked for explicitly, that is an error;
    the GPU default of one video falls back to none, with a warning."""
    wanted = default_video_episodes(device) if configured is None else int(configured)
    if wanted <= 0 or _has_mp4_writer():
        return max(wanted, 0)
    if configured is not None:
        raise ValueError(
            f"eval.video_episodes={configured}: {VIDEO_WRITER_HINT}; or set eval.video_episodes=0"
        )
    warnings.warn(
        f"no evaluation videos (eval.video_episodes defaults to 1 on a GPU): {VIDEO_WRITER_HINT}",
        stacklevel=2,
    )
    return 0


def add_frames(slots: Sequence[Any], env: Any, which: Sequence[int] | None = None) -> None:
    """Append the current frame of each env in ``which`` (default: all) whose episode is filmed."""
    which = range(len(slots)) if which is None else which
    filmed = [i for i in which if slots[i] is not None and slots[i].frames is not None]
    if not filmed:
        return
    frames = render_frames(env).numpy()
    for i in filmed:
        slots[i].frames.append(frames[i])


def write_video(path: Path, frames: Sequence[np.ndarray], fps: int) -> Path:
    """Write uint8 frames [H, W, 3] as an mp4 (imageio's ffmpeg)."""
    # optional dependency (app extra): writing videos
    import imageio

    if not _has_mp4_writer():
        raise ImportError(VIDEO_WRITER_HINT)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimwrite(path, list(frames), fps=fps)
    return path


_warned: set[str] = set()


def log_videos(logger: Any, result: dict[str, Any], step: int, prefix: str) -> list[str]:
    """Send every video of an evaluation result to ``logger.log_video`` as uint8 [1, T, 3, H, W],
    named ``{prefix}/video_seed{seed}``. A logger that lacks its video backend (TorchRL's CSV logger
    needs torchcodec, W&B and TensorBoard need moviepy) gets a warning once; the mp4 files in the
    run directory stay. Returns the names logged."""
    # optional dependency (app extra): writing videos
    import imageio.v3 as iio

    logged = []
    for episode in result.get("per_episode", []):
        path = episode.get("video")
        if not path or logger is None:
            continue
        frames = torch.from_numpy(np.ascontiguousarray(iio.imread(path)))  # [T, H, W, 3]
        video = frames.permute(0, 3, 1, 2).unsqueeze(0)  # [1, T, 3, H, W]
        name = f"{prefix}/video_seed{episode['seed']}"
        try:
            logger.log_video(name, video, step=step)
        except ImportError as err:
            kind = type(logger).__name__
            if kind not in _warned:
                _warned.add(kind)
                warnings.warn(
                    f"{kind} cannot log videos here ({err}); they stay in {Path(path).parent}", stacklevel=2
                )
            continue
        logged.append(name)
    return logged
