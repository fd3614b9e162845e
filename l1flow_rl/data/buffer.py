"""``make_chunk_buffer``: episodes -> a seeded TorchRL ``TensorDictReplayBuffer`` of chunk windows
(read-only over demonstrations, or writable for online data with ``capacity``)."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import TensorDictReplayBuffer
from torchrl.data.replay_buffers.writers import ImmutableDatasetWriter

from l1flow_rl.data.chunks import ActionPad, ChunkLayout, ChunkStorage, ChunkWindowSampler
from l1flow_rl.data.episodes import EpisodeDataError, episode_bounds
from l1flow_rl.data.loading import SOURCE_FILE
from l1flow_rl.data.metadata import EpisodeMetadata, episodes_metadata, strip_metadata
from l1flow_rl.data.online import CORE_KEYS, EpisodeWriter
from l1flow_rl.data.publish import publish_dir
from l1flow_rl.data.rl_windows import next_key

__all__ = ["action_pad_for", "make_chunk_buffer"]

_STORAGE_METADATA = "storage_metadata.json"  # what TorchRL's storage checkpointer writes on dumps()


def action_pad_for(control: str | None) -> ActionPad:
    """The padding past an episode's end for a control kind: zero motion for delta control, the
    last action repeated for absolute control (and when the data do not say)."""
    return "delta" if control == "delta" else "repeat"


def _spec(data: TensorDictBase) -> dict[str, tuple]:
    return {
        str(k): (tuple(v.shape), str(v.dtype)) for k, v in data.items(include_nested=True, leaves_only=True)
    }


def _reopen(directory: Path, n: int, layout: ChunkLayout) -> ChunkStorage:
    storage = ChunkStorage(n, layout=layout, scratch_dir=directory, existsok=True, auto_cleanup=False)
    storage.loads(directory)  # same directory as scratch_dir: TorchRL maps the files, no copy
    return storage


def _open_storage(
    episodes: TensorDictBase,
    layout: ChunkLayout,
    storage_dir: str | os.PathLike | None,
    meta: EpisodeMetadata,
) -> ChunkStorage:
    n = episodes.shape[0]
    memmap_dir = meta.extra.get("memmap_dir")
    saved = Path(memmap_dir) if memmap_dir else None
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
        (tmp / SOURCE_FILE).write_text(json.dumps({"fingerprint": None, "metadata": meta.to_json()}))
        if not publish_dir(tmp, directory):  # another process stored the same episodes first
            return _open_storage(episodes, layout, storage_dir, meta)  # checks that they match
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return _reopen(directory, n, layout)


def _check_rl_entries(
    episodes: TensorDictBase, reward_key: NestedKey, observation_key: NestedKey, meta: EpisodeMetadata
) -> None:
    """RL needs recorded rewards and the ('next', ...) entries; say which file lacks what."""
    if reward_key == ("next", "reward") and meta.has_rewards is False:
        raise EpisodeDataError(
            f"{meta.describe()}: records no rewards (its ('next', 'reward') is a placeholder), so no "
            "chunk return can be computed; use demonstrations recorded with rewards, or name another "
            "reward entry with reward_key (e.g. ('next', 'sparse_reward') for ManiSkill files)"
        )
    keys = episodes.keys(include_nested=True)
    for key in (reward_key, next_key(observation_key), ("next", "terminated")):
        if key not in keys:
            raise EpisodeDataError(
                f"{meta.describe()}: rl_horizon needs the {key!r} entry, which the episodes lack "
                f"(has {sorted(map(str, episodes.keys(True, True)))})"
            )


def make_chunk_buffer(
    episodes: TensorDictBase | None,
    obs_horizon: int = 2,
    pred_horizon: int = 16,
    batch_size: int = 256,
    seed: int = 0,
    *,
    action_pad: ActionPad | str = "auto",
    gripper_dims: Sequence[int] = (-1,),
    max_pad_after: int | None = None,
    rl_horizon: int | None = None,
    gamma: float = 0.99,
    reward_key: NestedKey = ("next", "reward"),
    capacity: int | None = None,
    keys: Sequence[NestedKey] = CORE_KEYS,
    storage_dir: str | os.PathLike | None = None,
    prefetch: int | None = None,
    source: str | None = None,
    anchor_key: NestedKey | None = None,
    terminated_episodes_only: bool = False,
) -> TensorDictReplayBuffer:
    """A replay buffer whose ``sample()`` returns chunk windows with Diffusion Policy's edge padding.

    Each sample holds ``"observation"`` [B, To, ...], ``"action_chunk"`` [B, H, A],
    ``"action_is_pad"`` [B, H] (True on padded steps), ``"episode"`` [B], ``"step"`` [B] (the window's
    current step in its episode), the current step's ``("next", ...)`` entries (without the next
    observation) and ``"index"`` [B, To + H + 2] (the storage rows read, then the episode's first and
    end rows). See :mod:`l1flow_rl.data.chunks` for the windows.

    With ``rl_horizon=h`` the ``"next"`` entries are the chunk's instead, for a chunked critic (see
    :mod:`l1flow_rl.data.rl_windows`): ``("next", "reward")`` [B, 1] the discounted return of the h
    executed actions ``action_chunk[:, To-1 : To-1+h]``, ``("next", "observation")`` [B, To, ...] the
    history at t+h, ``("next", "done" | "terminated" | "truncated")`` [B, 1], and ``"chunk_valid"``
    [B, 1].

    Args:
        episodes: steps in the layout of :func:`load_episodes` (None: an empty writable buffer).
        obs_horizon: To, the observations a window holds.
        pred_horizon: H, the actions of a window's chunk.
        batch_size: windows per ``sample()``.
        seed: seeds the buffer's generator; the same seed gives the same batches (with ``prefetch``
            above 1 the prefetch threads may hand batches back in another order).
        action_pad: ``"repeat"``, ``"delta"``, or ``"auto"``: from the control the episodes' metadata
            records (``"delta"`` for delta control, else ``"repeat"``).
        gripper_dims: action dimensions ``"delta"`` padding keeps (the gripper command).
        max_pad_after: cap on padded steps after an episode's end (None: H - To).
        rl_horizon: h, executed actions per chunk for the RL entries (None: imitation only). Data
            whose metadata says they hold no rewards are refused (naming the file).
        gamma: discount of the chunk return.
        reward_key: the per-step reward the chunk return sums.
        capacity: make the buffer writable with room for this many steps: ``extend`` then takes
            TorchRL collector batches (unfinished episodes are held until they end) or complete
            episodes, stored contiguously with fresh episode ids (see :mod:`l1flow_rl.data.online`).
            ``episodes``, when given, are written first.
        keys: entries a writable buffer stores per step (the same for demonstrations and online data).
        storage_dir: keep the memory-mapped storage under this directory; for read-only buffers an
            existing one with the same episodes is reused. Without it, episodes from
            ``load_episodes(memmap_dir=...)`` are used in place and others go to a temporary directory.
        prefetch: batches prepared ahead by background threads.
        source: a name for the data in error messages (default: the file the episodes came from).
        anchor_key: anchor windows only at rows where this stored entry equals 1 (see
            :class:`~l1flow_rl.data.chunks.ChunkLayout`); None: at every row.
        terminated_episodes_only: windows only in episodes that end in a terminal state (success
            here); filtered behaviour cloning's online data.

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
    if episodes is None and capacity is None:
        raise ValueError("make_chunk_buffer needs episodes, or a capacity for an (empty) writable buffer")
    if episodes is not None and (not isinstance(episodes, TensorDictBase) or episodes.batch_dims != 1):
        raise TypeError(
            f"episodes must be a TensorDict of steps with batch dims [N], got {type(episodes).__name__}"
        )
    meta = episodes_metadata(episodes) if episodes is not None else EpisodeMetadata()
    name = source or meta.source or ("online episodes" if episodes is None else "episodes")
    if episodes is not None:
        for key in ("episode", "observation", "action"):
            if key not in episodes.keys():  # noqa: SIM118 (TensorDict has no __contains__)
                raise KeyError(f"episodes lack the {key!r} entry (has {sorted(map(str, episodes.keys()))})")
        if rl_horizon is not None:
            _check_rl_entries(
                episodes,
                reward_key,
                "observation",
                EpisodeMetadata.from_dict({**meta.__dict__, "source": name}),
            )
    if action_pad == "auto":
        action_pad = action_pad_for(meta.control)
    layout = ChunkLayout(
        obs_horizon=obs_horizon,
        pred_horizon=pred_horizon,
        action_pad=action_pad,  # type: ignore[arg-type]
        gripper_dims=tuple(gripper_dims),
        max_pad_after=max_pad_after,
        rl_horizon=rl_horizon,
        gamma=gamma,
        reward_key=reward_key,
        anchor_key=anchor_key,
        terminated_episodes_only=terminated_episodes_only,
        source=name,
    )
    generator = torch.Generator().manual_seed(seed)
    if capacity is not None:
        return _writable_buffer(
            episodes, layout, capacity, keys, storage_dir, batch_size, prefetch, generator
        )
    episodes, _ = strip_metadata(episodes)  # the storage keeps it once
    if "step" not in episodes.keys():  # noqa: SIM118
        start, _ = episode_bounds(episodes.get("episode"), name)
        episodes = episodes.copy()  # shallow: the caller's TensorDict keeps its entries
        episodes.set("step", torch.arange(episodes.shape[0]) - start)
    storage = _open_storage(episodes, layout, storage_dir, meta)
    storage.metadata = meta
    sampler = ChunkWindowSampler(layout)
    sampler.validate(storage)
    return TensorDictReplayBuffer(
        storage=storage,
        sampler=sampler,
        writer=ImmutableDatasetWriter(),  # read-only demonstrations: the stored copy must match its source
        batch_size=batch_size,
        prefetch=prefetch,
        generator=generator,
    )


def _writable_buffer(episodes, layout, capacity, keys, storage_dir, batch_size, prefetch, generator):
    if capacity < 1:
        raise ValueError(f"capacity must be >= 1 steps, got {capacity}")
    if storage_dir is not None and Path(storage_dir).exists() and any(Path(storage_dir).iterdir()):
        raise EpisodeDataError(f"{storage_dir}: exists and is not empty; a writable buffer starts empty")
    scratch = storage_dir if storage_dir is not None else tempfile.mkdtemp(prefix="l1flow_online_")
    storage = ChunkStorage(
        capacity, layout=layout, scratch_dir=scratch, existsok=True, auto_cleanup=storage_dir is None
    )
    writer = EpisodeWriter(
        keys, require_rewards=layout.rl_horizon is not None and layout.reward_key == ("next", "reward")
    )
    rb = TensorDictReplayBuffer(
        storage=storage,
        sampler=ChunkWindowSampler(layout),
        writer=writer,
        batch_size=batch_size,
        prefetch=prefetch,
        generator=generator,
    )
    if episodes is not None:
        rb.extend(episodes)
    return rb
