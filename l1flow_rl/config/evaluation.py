"""Evaluation settings (``eval``): episodes, envs, seeds, protocol."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["EvalConfig"]


@dataclass
class EvalConfig:
    episodes: int = 50
    num_envs: int = 2
    seed: int = 1000
    video_episodes: int = 0
    deterministic: bool = False
