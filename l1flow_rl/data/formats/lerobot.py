"""LeRobot datasets on local disk, read through TorchRL's ``LeRobotExperienceReplay``.

TorchRL serves a LeRobot dataset offline from its converted, memory-mapped copy
(``LeRobotExperienceReplay(repo_id, root=ROOT, download=False)`` reads ``ROOT/<repo_id>``), which is
what this reader opens: pass that directory. LeRobot's own layout (``meta/info.json`` plus parquet
files) is read by :mod:`l1flow_rl.data.formats.lerobot_v3`. Here, video-encoded cameras would need
``torchcodec`` (TorchRL's decoder), which is not installed, and are refused; cameras stored as frames
work. LeRobot keeps no observation after
an episode's last action, and its control kind is not recorded (the task config decides).
"""

from __future__ import annotations

from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.data.datasets.lerobot import LeRobotExperienceReplay

from l1flow_rl.data.episodes import (
    EpisodeDataError,
    assemble_episode,
    check_finite,
    to_uint8_image,
    where,
)
from l1flow_rl.data.formats.base import EpisodeFile

__all__ = ["LeRobotDirectory", "is_raw_lerobot", "is_torchrl_lerobot"]


def is_torchrl_lerobot(path: Path) -> bool:
    return path.is_dir() and (path / "meta.json").is_file() and (path / "episode.memmap").is_file()


def is_raw_lerobot(path: Path) -> bool:
    return path.is_dir() and (path / "meta" / "info.json").is_file()


class LeRobotDirectory(EpisodeFile):
    """Reader for TorchRL's converted copy of a LeRobot dataset.

    Args:
        path: ``ROOT/<repo_id>`` as written by ``LeRobotExperienceReplay(repo_id, root=ROOT)``.
        camera: which ``observation.images.<camera>`` to use as ``"rgb"``; ``"auto"`` takes the only
            one when there is exactly one, ``None`` makes a state-only observation.
    """

    format_name = "lerobot"

    def __init__(self, path: Path, *, camera: str | None = "auto") -> None:
        super().__init__(path)
        if is_raw_lerobot(path):
            raise EpisodeDataError(
                f"{path}: LeRobot's own layout (meta/info.json), not TorchRL's copy; read it with "
                "l1flow_rl.data.formats.lerobot_v3.LeRobotV3Directory (load_episodes picks it)"
            )

        try:
            replay = LeRobotExperienceReplay(path.name, root=path.parent, download=False, decode_video=False)
        except (RuntimeError, OSError, KeyError, ValueError) as err:
            raise EpisodeDataError(f"{path}: cannot open as TorchRL's LeRobot copy: {err}") from err
        self.data = replay.storage.get(slice(None))
        for key in ("action", "episode", ("observation", "state")):
            if key not in self.data.keys(include_nested=True):
                raise EpisodeDataError(
                    f"{where(path, key='.'.join(key) if isinstance(key, tuple) else key)}: missing"
                )
        cameras = (
            list(self.data.get(("observation", "image")).keys())
            if ("observation", "image") in self.data.keys(include_nested=True)
            else []
        )
        videos = (path / "video_refs.json").is_file()
        if camera == "auto":
            if len(cameras) > 1:
                raise EpisodeDataError(
                    f"{path}: several cameras {cameras}; pass camera=<one of them> (or None)"
                )
            camera = cameras[0] if cameras else None
        if camera is not None and camera not in cameras:
            reason = " (video-encoded cameras need torchcodec, which is not installed)" if videos else ""
            raise EpisodeDataError(
                f"{where(path, key=f'observation.images.{camera}')}: not available{reason}"
            )
        self.camera = camera
        ids, counts = torch.unique_consecutive(self.data.get("episode").reshape(-1), return_counts=True)
        if ids.unique().numel() != ids.numel():
            raise EpisodeDataError(
                f"{where(path, key='episode_index')}: an episode's frames are not contiguous"
            )
        ends = torch.cumsum(counts, 0)
        self._rows = {int(e): (int(end - n), int(end)) for e, n, end in zip(ids, counts, ends)}

    @property
    def metadata(self) -> dict:
        keys = self.data.keys(include_nested=True)
        return {
            **super().metadata,
            "has_rewards": ("next", "reward") in keys,
            "has_final_observation": False,  # LeRobot stores no observation after the last action
        }

    def episode_ids(self) -> list[int]:
        return list(self._rows)

    def episode_length(self, episode: int) -> int:
        start, end = self._rows[episode]
        return end - start

    def read_episode(self, episode: int) -> TensorDict:
        start, end = self._rows[episode]
        rows = self.data[start:end]
        steps = end - start
        action = check_finite(rows.get("action").float().reshape(steps, -1), self.path, episode, "action")
        state = check_finite(
            rows.get(("observation", "state")).float().reshape(steps, -1),
            self.path,
            episode,
            "observation.state",
        )
        observation: torch.Tensor | dict = state
        if self.camera is not None:
            key = f"observation.images.{self.camera}"
            image = rows.get(("observation", "image", self.camera)).clone()
            observation = {
                "state": state,
                "rgb": to_uint8_image(image, self.path, episode, key, channels_last=False, float_max=1.0),
            }
        keys = rows.keys(include_nested=True)
        reward = rows.get(("next", "reward")).float().reshape(steps) if ("next", "reward") in keys else None
        if reward is not None:
            check_finite(reward, self.path, episode, "next.reward")
        terminated = bool(rows.get(("next", "done")).reshape(-1)[-1]) if ("next", "done") in keys else False
        return assemble_episode(episode, observation, action, reward=reward, terminated=terminated)
