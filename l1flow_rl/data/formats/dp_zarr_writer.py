"""Writing Diffusion Policy's zarr replay-buffer layout (what ``pusht_cchi_v7_replay.zarr`` holds).

``data/<key>`` arrays hold every step of every episode back to back and ``meta/episode_ends`` the
exclusive end row of each episode, as Diffusion Policy's ``ReplayBuffer`` reads them (zarr format 2,
which its zarr 2 readers open). Arrays beyond Diffusion Policy's own (e.g. ``data/reward``) are
allowed: its readers load only the keys they ask for. The store appears under its final name only
once complete.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["write_dp_zarr"]


def write_dp_zarr(
    path: str | os.PathLike,
    episodes: Sequence[Mapping[str, np.ndarray]],
    *,
    meta: Mapping[str, np.ndarray] | None = None,
    attrs: Mapping[str, object] | None = None,
) -> Path:
    """Write ``episodes`` (each ``{key: array [T, ...]}``, the same keys and trailing shapes in every
    episode) as a Diffusion Policy replay buffer at ``path``.

    Args:
        path: the ``.zarr`` directory to create; an existing one is replaced only once the new
            store is complete.
        episodes: per episode, ``data/<key>`` rows; every key of an episode has its number of steps.
        meta: extra per-episode ``meta/<key>`` arrays [E, ...] besides ``episode_ends``.
        attrs: JSON-serialisable facts stored in the root group's attributes.

    Example:
        >>> ep = {"action": np.zeros((3, 2), np.float32), "state": np.zeros((3, 5), np.float32)}
        >>> write_dp_zarr("/tmp/doc_example.zarr", [ep, ep]).name  # doctest: +SKIP
        'doc_example.zarr'
    """
    # optional dependency (pusht extra): Diffusion Policy's zarr stores
    import zarr

    path = Path(path)
    if not episodes:
        raise ValueError(f"{path}: no episodes to write")
    keys = list(episodes[0])
    lengths = []
    for e, ep in enumerate(episodes):
        if list(ep) != keys:
            raise ValueError(f"{path}: episode {e} has keys {list(ep)}, episode 0 has {keys}")
        steps = {k: len(v) for k, v in ep.items()}
        if len(set(steps.values())) != 1 or not next(iter(steps.values())):
            raise ValueError(
                f"{path}: episode {e}: arrays must share a non-zero number of steps, got {steps}"
            )
        lengths.append(next(iter(steps.values())))
    ends = np.cumsum(lengths).astype(np.int64)
    for n in meta.values() if meta else ():
        if len(n) != len(episodes):
            raise ValueError(f"{path}: meta arrays need one row per episode ({len(episodes)}), got {len(n)}")

    tmp = path.parent / f".{path.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        root = zarr.open_group(str(tmp), mode="w", zarr_format=2)
        data, meta_group = root.create_group("data"), root.create_group("meta")
        for key in keys:
            values = np.concatenate([np.asarray(ep[key]) for ep in episodes])
            rows = max(1, min(len(values), (1 << 20) // max(1, values[0].nbytes)))  # ~1 MiB chunks
            arr = data.create_array(
                key, shape=values.shape, dtype=values.dtype, chunks=(rows, *values.shape[1:])
            )
            arr[:] = values
        arr = meta_group.create_array("episode_ends", shape=ends.shape, dtype=ends.dtype, chunks=ends.shape)
        arr[:] = ends
        for key, values in (meta or {}).items():
            values = np.asarray(values)
            arr = meta_group.create_array(key, shape=values.shape, dtype=values.dtype, chunks=values.shape)
            arr[:] = values
        root.attrs.update(dict(attrs or {}))
        if path.exists():
            shutil.rmtree(path)
        os.replace(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path
