"""``make_chunk_buffer``: episodes -> a seeded TorchRL ``TensorDictReplayBuffer`` of chunk windows."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.data import TensorDictReplayBuffer
from torchrl.data.replay_buffers.writers import ImmutableDatasetWriter

from l1flow_rl.data.chunks import ActionPad, ChunkLayout, ChunkStorage, ChunkWindowSampler
from l1flow_rl.data.episodes import EpisodeDataError, episode_bounds
from l1flow_rl.data.loading import SOURCE_FILE, episodes_metadata

__all__ = ["make_chunk_buffer"]

_STORAGE_METADATA = "storage_metadata.json"  # what TorchRL's storage checkpointer writes on dumps()


def _auto_action_pad(meta: dict) -> ActionPad:
    # ManiSkill names its delta controllers *_delta_*; every other known format is absolute control.
    return "delta" if "delta" in str(meta.get("control_mode") or "") else "repeat"


def _spec(data: TensorDictBase) -> dict[str, tuple]:
    return {
        str(k): (tuple(v.shape), str(v.dtype)) for k, v in data.items(include_nested=True, leaves_only=True)
    }


def _reopen(directory: Path, n: int, layout: ChunkLayout) -> ChunkStorage:
    storage = ChunkStorage(n, layout=layout, scratch_dir=directory, existsok=True, auto_cleanup=False)
    storage.loads(directory)  # same directory as scratch_dir: TorchRL maps the files, no copy
    return storage


def _open_storage(
    episodes: TensorDictBase, layout: ChunkLayout, storage_dir: str | os.PathLike | None, meta: dict
) -> ChunkStorage:
    n = episodes.shape[0]
    saved = Path(meta["memmap_dir"]) if meta.get("memmap_dir") else None
    if storage_dir is None and saved is not None and (saved / _STORAGE_METADATA).is_file():
        return _reopen(saved, n, layout)  # load_episodes(memmap_dir=...) already made a TorchRL storage
    if storage_dir is None:
        storage = ChunkStorage(n, layout=layout)  # a temporary directory, removed at exit
        storage.set(range(n), episodes)
        return storage
    directory = Path(storage_dir)
    if (directory / _STORAGE_METADATA).is_file():
        storage = _reopen(directory, n, layout)
        stored = storage.get(slice(None))
        same = (
            len(storage) == n
            and _spec(stored[:0]) == _spec(episodes[:0])
            and torch.equal(stored.get("episode"), episodes.get("episode"))
            and torch.equal(stored.get(layout.action_key), episodes.get(layout.action_key))
        )
        if not same:
            raise EpisodeDataError(
                f"{directory}: holds a stored copy of other episodes ({len(storage)} steps) than the {n} "
                "steps given; use another storage_dir or delete this one"
            )
        return storage
    if directory.exists() and any(directory.iterdir()):
        raise EpisodeDataError(
            f"{directory}: exists, is not empty and holds no stored episodes; choose another storage_dir"
        )
    tmp = directory.parent / f".{directory.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        storage = ChunkStorage(n, layout=layout, scratch_dir=tmp, existsok=True, auto_cleanup=False)
        storage.set(range(n), episodes)
        storage.dumps(tmp)
        (tmp / SOURCE_FILE).write_text(json.dumps({"fingerprint": None, "metadata": meta}))
        if directory.exists():
            directory.rmdir()
        os.replace(tmp, directory)  # a half-written copy never carries the final name
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return _reopen(directory, n, layout)


def make_chunk_buffer(
    episodes: TensorDictBase,
    obs_horizon: int = 2,
    pred_horizon: int = 16,
    batch_size: int = 256,
    seed: int = 0,
    *,
    action_pad: ActionPad | str = "auto",
    gripper_dims: Sequence[int] = (-1,),
    max_pad_after: int | None = None,
    storage_dir: str | os.PathLike | None = None,
    prefetch: int | None = None,
    source: str | None = None,
) -> TensorDictReplayBuffer:
    """A replay buffer whose ``sample()`` returns chunk windows with Diffusion Policy's edge padding.

    Each sample holds ``"observation"`` [B, To, ...], ``"action_chunk"`` [B, H, A],
    ``"action_is_pad"`` [B, H] (True on padded steps), ``"episode"`` [B], ``"step"`` [B] (the window's
    current step in its episode), the current step's ``("next", ...)`` entries and ``"index"``
    [B, To + H] (the storage rows read). See :mod:`l1flow_rl.data.chunks` for the windows.

    Args:
        episodes: steps in the layout of :func:`load_episodes`.
        obs_horizon, pred_horizon: To and H.
        batch_size: windows per ``sample()``.
        seed: seeds the buffer's generator; the same seed gives the same batches (with ``prefetch``
            above 1 the prefetch threads may hand batches back in another order).
        action_pad: ``"repeat"``, ``"delta"``, or ``"auto"``: ``"delta"`` when the episodes come from a
            file recorded with a delta controller (ManiSkill ``pd_*_delta_*``), else ``"repeat"``.
        gripper_dims: action dimensions ``"delta"`` padding keeps (the gripper command).
        max_pad_after: cap on padded steps after an episode's end (None: H - To).
        storage_dir: keep the memory-mapped storage under this directory; an existing one with the
            same episodes is reused. Without it, episodes from ``load_episodes(memmap_dir=...)`` are
            used in place and others go to a temporary directory.
        prefetch: batches prepared ahead by background threads.
        source: a name for the data in error messages (default: the file the episodes came from).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from l1flow_rl.data import make_chunk_buffer
        >>> steps = TensorDict(
        ...     {"episode": torch.arange(3).repeat_interleave(10), "observation": torch.randn(30, 5),
        ...      "action": torch.randn(30, 2)},
        ...     batch_size=[30],
        ... )
        >>> rb = make_chunk_buffer(steps, obs_horizon=2, pred_horizon=16, batch_size=64, seed=0)
        >>> batch = rb.sample()
        >>> batch["observation"].shape, batch["action_chunk"].shape, batch["action_is_pad"].shape
        (torch.Size([64, 2, 5]), torch.Size([64, 16, 2]), torch.Size([64, 16]))
    """
    if not isinstance(episodes, TensorDictBase) or episodes.batch_dims != 1:
        raise TypeError(
            f"episodes must be a TensorDict of steps with batch dims [N], got {type(episodes).__name__}"
        )
    for key in ("episode", "observation", "action"):
        if key not in episodes.keys():  # noqa: SIM118 (TensorDict has no __contains__)
            raise KeyError(f"episodes lack the {key!r} entry (has {sorted(map(str, episodes.keys()))})")
    meta = episodes_metadata(episodes)
    if "step" not in episodes.keys():  # noqa: SIM118
        start, _ = episode_bounds(episodes.get("episode"), source or meta.get("source", "episodes"))
        episodes = episodes.copy()  # shallow: the caller's TensorDict keeps its entries
        episodes.set("step", torch.arange(episodes.shape[0]) - start)
    if action_pad == "auto":
        action_pad = _auto_action_pad(meta)
    layout = ChunkLayout(
        obs_horizon=obs_horizon,
        pred_horizon=pred_horizon,
        action_pad=action_pad,  # type: ignore[arg-type]
        gripper_dims=tuple(gripper_dims),
        max_pad_after=max_pad_after,
        source=source or meta.get("source", "episodes"),
    )
    storage = _open_storage(episodes, layout, storage_dir, meta)
    sampler = ChunkWindowSampler(layout)
    sampler.validate(storage)
    return TensorDictReplayBuffer(
        storage=storage,
        sampler=sampler,
        writer=ImmutableDatasetWriter(),  # read-only demonstrations: the stored copy must match its source
        batch_size=batch_size,
        prefetch=prefetch,
        generator=torch.Generator().manual_seed(seed),
    )
