"""What every demonstration-file reader provides: episode ids, cheap lengths, one episode at a time."""

from __future__ import annotations

import abc
from pathlib import Path

import h5py
from tensordict import TensorDict

from l1flow_rl.data.episodes import EpisodeDataError

__all__ = ["EpisodeFile", "open_h5"]


class EpisodeFile(abc.ABC):
    """A demonstration file opened for reading. Lengths come from metadata, so the total size of a
    dataset is known before any episode is read (memory-mapped storage is allocated once)."""

    format_name: str = ""

    def __init__(self, path: Path) -> None:
        self.path = path

    @property
    def metadata(self) -> dict:
        """Facts about the data that consumers may use (format, source, control mode, ...)."""
        return {"format": self.format_name, "source": str(self.path)}

    @abc.abstractmethod
    def episode_ids(self) -> list[int]: ...

    @abc.abstractmethod
    def episode_length(self, episode: int) -> int: ...

    @abc.abstractmethod
    def read_episode(self, episode: int) -> TensorDict:
        """One episode in the layout of :mod:`l1flow_rl.data.episodes`, validated."""

    def episode_labels(self) -> dict[int, str] | None:
        """Each episode's quality label (``expert``, ``noisy``, ...; see ``demos.quality=mixed``),
        None when the file records none."""
        return None

    def close(self) -> None:  # noqa: B027 - readers without open handles need nothing
        pass

    def __enter__(self) -> EpisodeFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_h5(path: Path) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except OSError as err:
        raise EpisodeDataError(
            f"{path}: cannot open as HDF5 (missing, truncated or another format): {err}"
        ) from err
