"""Camera streams as mp4 through PyAV (FFmpeg's libraries): encode frames back to back, decode the
frames of one time window. LeRobot v3 keeps each camera of many episodes in one file and finds an
episode by its start time in that file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from l1flow_rl.data.episodes import EpisodeDataError

__all__ = ["LEROBOT_TOLERANCE_S", "VideoWriter", "decode_window"]

#: how far a decoded frame's time may lie from the time asked for (LeRobot's default ``tolerance_s``)
LEROBOT_TOLERANCE_S = 1e-4


def _av():
    try:
        # the lerobot extra: mp4 camera streams
        import av
    except ImportError as err:
        raise ImportError(
            "LeRobot camera videos need PyAV, which is not installed: pip install 'l1flow-rl[lerobot]'"
        ) from err
    return av


class VideoWriter:
    """Frames [T, H, W, 3] uint8 appended to one mp4 at ``fps``; frame i is shown at i / fps.

    H.264 in yuv420p (the codec and pixel format LeRobot's decoders read everywhere), with a key frame
    every 2 frames as LeRobot records, so an episode in the middle of a file decodes without reading
    the file from its start. The colour conversion and compression are lossy (see the writer)."""

    def __init__(self, path: Path, fps: int, height: int, width: int, *, crf: int = 18) -> None:
        av = _av()
        if height % 2 or width % 2:
            raise ValueError(
                f"{path}: H.264 in yuv420p needs an even height and width, got {height}x{width}; store this "
                "camera as images instead"
            )
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._container = av.open(str(path), mode="w")
        self._stream = self._container.add_stream("libx264", rate=int(fps))
        self._stream.width, self._stream.height = width, height
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"crf": str(crf), "g": "2"}
        self.frames = 0

    def write(self, frames: np.ndarray) -> None:
        av = _av()
        for frame in frames:
            video_frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            video_frame.pts = self.frames
            for packet in self._stream.encode(video_frame):
                self._container.mux(packet)
            self.frames += 1

    def close(self) -> None:
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()


def decode_window(
    path: Path, timestamps: np.ndarray, *, tolerance_s: float = LEROBOT_TOLERANCE_S, key: str = ""
) -> np.ndarray:
    """The frames shown at ``timestamps`` (seconds in the file, increasing) as uint8 [T, H, W, 3].

    Seeks to the key frame before the first time and decodes up to the last; every time must have a
    frame within ``tolerance_s``, else the file and the episode table disagree, which is an error."""
    av = _av()
    if not path.is_file():
        raise EpisodeDataError(f"{path}: missing (the video of {key!r})")
    first, last = float(timestamps[0]), float(timestamps[-1])
    times: list[float] = []
    frames: list[np.ndarray] = []
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            base = stream.time_base
            container.seek(int(max(first - tolerance_s, 0.0) / base), stream=stream, backward=True)
            for frame in container.decode(stream):
                t = float(frame.pts * base)
                if t < first - tolerance_s:
                    continue
                if t > last + tolerance_s:
                    break
                times.append(t)
                frames.append(frame.to_ndarray(format="rgb24"))
    except (av.error.FFmpegError, IndexError) as err:
        raise EpisodeDataError(f"{path}: cannot decode the video of {key!r} ({err})") from err
    if not frames:
        raise EpisodeDataError(
            f"{path}: no frame of {key!r} between {first:.4f} s and {last:.4f} s (the episode table's "
            "timestamps lie outside the video)"
        )
    found = np.asarray(times)
    nearest = np.abs(found[None, :] - timestamps[:, None]).argmin(1)
    gap = np.abs(found[nearest] - timestamps)
    if (gap > tolerance_s).any():
        i = int(np.argmax(gap > tolerance_s))
        raise EpisodeDataError(
            f"{path}: no frame of {key!r} at {float(timestamps[i]):.4f} s (row {i} of the episode; the "
            f"nearest is {float(found[nearest[i]]):.4f} s, more than {tolerance_s} s away)"
        )
    return np.stack([frames[j] for j in nearest])
