"""Evaluation videos: frames of the filmed episodes, written as mp4 into the run directory and
handed to a TorchRL logger through its video API (``Logger.log_video``)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["add_frames", "default_video_episodes", "log_videos", "write_video"]


def default_video_episodes(device: str | torch.device) -> int:
    """Episodes filmed when ``eval.video_episodes`` is not set: one on a GPU, none on the CPU, where
    the first rendered frame costs seconds (the renderer starts) and every frame slows the episode."""
    return 1 if torch.device(device).type == "cuda" else 0


def add_frames(slots: Sequence[Any], env: Any, which: Sequence[int] | None = None) -> None:
    """Append the current frame of each env in ``which`` (default: all) whose episode is filmed."""
    from l1flow_rl.envs.per_env import render_frames

    which = range(len(slots)) if which is None else which
    filmed = [i for i in which if slots[i] is not None and slots[i].frames is not None]
    if not filmed:
        return
    frames = render_frames(env).numpy()
    for i in filmed:
        slots[i].frames.append(frames[i])


def write_video(path: Path, frames: Sequence[np.ndarray], fps: int) -> Path:
    """Write uint8 frames [H, W, 3] as an mp4 (imageio's ffmpeg)."""
    import imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimwrite(path, list(frames), fps=fps)
    return path


_warned: set[str] = set()


def log_videos(logger: Any, result: dict[str, Any], step: int, prefix: str) -> list[str]:
    """Send every video of an evaluation result to ``logger.log_video`` as uint8 [1, T, 3, H, W],
    named ``{prefix}/video_seed{seed}``. A logger that lacks its video backend (TorchRL's CSV logger
    needs torchcodec, W&B and TensorBoard need moviepy) gets a warning once; the mp4 files in the
    run directory stay. Returns the names logged."""
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
