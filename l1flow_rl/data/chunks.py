"""Chunk windows out of a flat step storage: which rows to read (the sampler) and how to read them
(the storage), with Diffusion Policy's edge padding.

A window is anchored at a *current step* t of an episode of length L. It reads

* observations at t-To+1 ... t, where steps before the episode start repeat the first observation;
* actions at t-To+1 ... t-To+H (so chunk step To-1 is the action taken at t), where steps before
  the start repeat the first action and steps after the end follow ``action_pad``: ``"repeat"`` the
  last action (absolute control), or ``"delta"`` zero motion on every non-gripper dimension with the
  last gripper command kept (delta control, as ManiSkill's Diffusion Policy baseline pads).

Every step of every episode is an anchor by default, so a chunk ends with up to H-To padded steps;
``max_pad_after`` caps that (Diffusion Policy's ``pad_after = n_action_steps - 1``), and an episode
too short to give any window under the cap is an error. ``"action_is_pad"`` marks the padded chunk
steps (both ends) so a loss can leave them out.

With ``rl_horizon=h`` a window also carries what a chunked critic needs (see
:mod:`l1flow_rl.data.rl_windows`): the discounted return of the h executed actions, the
history-stacked observation at t+h, done/terminated/truncated and ``"chunk_valid"``.

TorchRL's ``SliceSampler`` pads only at the end and ``Sequence`` returns flat [B * H] batches that
read every key at every window row; this pair reads observations at To rows and actions at H rows,
which keeps image batches small.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.data import LazyMemmapStorage
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

from l1flow_rl.data.episodes import EpisodeDataError, episode_bounds, where
from l1flow_rl.data.metadata import EpisodeMetadata, merge_metadata, strip_metadata
from l1flow_rl.data.rl_windows import next_key, read_rl_targets

__all__ = ["ChunkLayout", "ChunkStorage", "ChunkWindowSampler"]

ActionPad = Literal["repeat", "delta"]


@dataclass(frozen=True)
class ChunkLayout:
    """Shape and padding of a chunk window; shared by :class:`ChunkWindowSampler` and :class:`ChunkStorage`.

    Args:
        obs_horizon: To, observation steps per window (the last is the current step).
        pred_horizon: H, action steps per chunk (H >= To).
        action_pad: ``"repeat"`` (absolute actions) or ``"delta"`` (delta control) padding after the end.
        gripper_dims: action dimensions kept (not zeroed) by ``"delta"`` padding; ManiSkill's Panda
            controllers put the gripper last.
        max_pad_after: at most this many padded steps after an episode's end (None: H - To, every
            step is a window's current step).
        rl_horizon: h, the executed actions per chunk for RL targets (None: no RL entries); at most
            H - To + 1 so that ``action_chunk[:, To-1 : To-1+h]`` lies inside the chunk.
        gamma: the discount of the chunk return.
        reward_key: the stored per-step reward the chunk return sums.
        anchor_key: a stored per-step entry; where given, only rows where it equals 1 are window
            anchors (DSRL: ``MultiStepActorWrapper``'s ``"counter"``, 1 at a chunk's first step, the
            only steps whose stored noise describes the actions from there on). None: every row.
        terminated_episodes_only: windows only in episodes whose last step is terminated (in the
            tasks here the only terminal state is success, the sparse reward's definition): filtered
            behaviour cloning's online data.
        source: a name for the data in error messages (a file path).
    """

    obs_horizon: int = 2
    pred_horizon: int = 16
    action_pad: ActionPad = "repeat"
    gripper_dims: tuple[int, ...] = (-1,)
    max_pad_after: int | None = None
    rl_horizon: int | None = None
    gamma: float = 0.99
    reward_key: NestedKey = ("next", "reward")
    observation_key: NestedKey = "observation"
    action_key: NestedKey = "action"
    chunk_key: NestedKey = "action_chunk"
    pad_key: NestedKey = "action_is_pad"
    anchor_key: NestedKey | None = None
    terminated_episodes_only: bool = False
    source: str = field(default="episodes", compare=False)

    def __post_init__(self) -> None:
        if self.obs_horizon < 1 or self.pred_horizon < self.obs_horizon:
            raise ValueError(
                f"need 1 <= obs_horizon <= pred_horizon, got obs_horizon={self.obs_horizon}, "
                f"pred_horizon={self.pred_horizon}"
            )
        if self.action_pad not in ("repeat", "delta"):
            raise ValueError(f"action_pad must be 'repeat' or 'delta', got {self.action_pad!r}")
        if (
            self.max_pad_after is not None
            and not 0 <= self.max_pad_after <= self.pred_horizon - self.obs_horizon
        ):
            raise ValueError(
                "max_pad_after must be in [0, pred_horizon - obs_horizon = "
                f"{self.pred_horizon - self.obs_horizon}] or None, got {self.max_pad_after}"
            )
        if self.rl_horizon is not None:
            most = self.pred_horizon - self.obs_horizon + 1
            if not 1 <= self.rl_horizon <= most:
                raise ValueError(
                    f"rl_horizon must be in [1, pred_horizon - obs_horizon + 1 = {most}] (the executed "
                    f"actions action_chunk[:, To-1 : To-1+h] must lie in the chunk), got {self.rl_horizon}"
                )
            if not 0.0 < self.gamma <= 1.0:
                raise ValueError(f"gamma must be in (0, 1], got {self.gamma}")
        object.__setattr__(self, "gripper_dims", tuple(int(d) for d in self.gripper_dims))

    @property
    def width(self) -> int:
        """Columns of a window index: To observation rows, H action rows, then the episode's first row
        and its end row (exclusive)."""
        return self.obs_horizon + self.pred_horizon + 2

    def is_window_index(self, index: Any) -> bool:
        return isinstance(index, Tensor) and index.dim() == 2 and index.shape[1] == self.width

    def arm_mask(self, action_dim: int) -> Tensor:
        """True on the action dimensions that ``"delta"`` padding zeroes."""
        mask = torch.ones(action_dim, dtype=torch.bool)
        for d in self.gripper_dims:
            if not -action_dim <= d < action_dim:
                raise ValueError(
                    f"gripper_dims {self.gripper_dims} out of range for actions of size {action_dim}"
                )
            mask[d] = False
        return mask


class ChunkWindowSampler(Sampler):
    """Draws window anchors uniformly over the valid current steps and returns window indices [B, To + H]
    (storage rows, clamped to the anchor's episode), to be read by :class:`ChunkStorage`.

    Random draws use the replay buffer's generator (``TensorDictReplayBuffer(generator=...)``), so a
    seeded buffer repeats its batches.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import TensorDictReplayBuffer
        >>> from l1flow_rl.data.chunks import ChunkLayout, ChunkStorage, ChunkWindowSampler
        >>> steps = TensorDict(
        ...     {"episode": torch.tensor([0, 0, 0, 1, 1]), "observation": torch.arange(5.0)[:, None],
        ...      "action": torch.arange(5.0)[:, None]},
        ...     batch_size=[5],
        ... )
        >>> layout = ChunkLayout(obs_horizon=2, pred_horizon=3)
        >>> storage = ChunkStorage(5, layout=layout)
        >>> storage.set(range(5), steps)
        >>> rb = TensorDictReplayBuffer(storage=storage, sampler=ChunkWindowSampler(layout), batch_size=4,
        ...                             generator=torch.Generator().manual_seed(0))
        >>> batch = rb.sample()
        >>> batch["observation"].shape, batch["action_chunk"].shape, batch["action_is_pad"].shape
        (torch.Size([4, 2, 1]), torch.Size([4, 3, 1]), torch.Size([4, 3]))
    """

    def __init__(self, layout: ChunkLayout) -> None:
        self.layout = layout
        self._cache: tuple[Any, Tensor, Tensor, Tensor] | None = None

    def _episode_table(self, storage: Storage) -> tuple[Tensor, Tensor, Tensor]:
        """(start row, end row) per stored row, and the valid anchor rows; recomputed when the storage
        changes."""
        alive = getattr(storage, "alive", None)
        key = (
            len(storage),
            int(getattr(storage, "_mutation_revision", 0)),
            int(getattr(storage, "revision", 0)),
        )
        if self._cache is None or self._cache[0] != key:
            if len(storage) == 0:
                raise EpisodeDataError(f"{self.layout.source}: the buffer holds no complete episode yet")
            data = storage.get(slice(None))
            start, end = episode_bounds(data.get("episode"), self.layout.source)
            rows = torch.arange(start.shape[0])
            valid = torch.ones_like(rows, dtype=torch.bool)
            if self.layout.max_pad_after is not None:
                # the chunk's last row t-To+H may lie at most max_pad_after rows past the episode's last row
                last_needed = rows - self.layout.obs_horizon + self.layout.pred_horizon
                valid = last_needed - (end - 1) <= self.layout.max_pad_after
            if self.layout.anchor_key is not None:
                valid &= self._anchor_rows(data)
            if self.layout.terminated_episodes_only:
                terminated = data.get(("next", "terminated")).reshape(start.shape[0], -1)[:, 0].bool()
                valid &= terminated[end - 1]
            if alive is not None:
                # online data: rows of overwritten episodes are dead; a short episode gives no window
                valid &= alive[: valid.shape[0]]
            elif not self.layout.terminated_episodes_only:
                self._check_every_episode_has_windows(data.get("episode"), start, valid)
            self._cache = (key, start, end, valid.nonzero().squeeze(1))
        return self._cache[1], self._cache[2], self._cache[3]

    def window_count(self, storage: Storage) -> int:
        """How many windows the stored episodes give (0 where none qualifies: e.g. no episode has
        ended in a terminal state yet with ``terminated_episodes_only``)."""
        return 0 if len(storage) == 0 else int(self._episode_table(storage)[2].numel())

    def _anchor_rows(self, data: TensorDictBase) -> Tensor:
        key = self.layout.anchor_key
        entry = data.get(key, default=None)
        if entry is None:
            raise EpisodeDataError(
                f"{self.layout.source}: anchor_key={key!r} names no stored entry "
                f"(has {sorted(map(str, data.keys(True, True)))})"
            )
        return entry.reshape(entry.shape[0], -1)[:, 0] == 1

    def _check_every_episode_has_windows(self, episode: Tensor, start: Tensor, valid: Tensor) -> None:
        starts = start.unique()
        per_episode = torch.zeros(start.shape[0], dtype=torch.long).index_add_(0, start, valid.long())[starts]
        if (per_episode == 0).any():
            first = int(starts[per_episode == 0][0])
            length = int((start == first).sum())
            raise EpisodeDataError(
                f"{where(self.layout.source, int(episode[first]), 'action')}: {length} steps is too short "
                f"for pred_horizon={self.layout.pred_horizon} with obs_horizon={self.layout.obs_horizon} "
                f"and at most max_pad_after={self.layout.max_pad_after} padded steps; it needs at least "
                f"{self.layout.pred_horizon - self.layout.obs_horizon + 1 - self.layout.max_pad_after} "
                "steps (raise max_pad_after, or drop the episode from the data)"
            )

    def validate(self, storage: Storage) -> None:
        """Check the stored episodes once, before training starts (errors name the episode)."""
        self._episode_table(storage)

    def sample(self, storage: Storage, batch_size: int) -> tuple[Tensor, dict]:
        start, end, anchors = self._episode_table(storage)
        if anchors.numel() == 0:
            what = "ended in a terminal state" if self.layout.terminated_episodes_only else "is long enough"
            raise EpisodeDataError(f"{self.layout.source}: no episode {what} to give a window")
        pick = torch.randint(anchors.numel(), (batch_size,), generator=self._rng)
        t = anchors[pick]
        t_start, t_last = start[t].unsqueeze(1), end[t].unsqueeze(1) - 1
        to, h = self.layout.obs_horizon, self.layout.pred_horizon
        obs_rows = torch.maximum(t.unsqueeze(1) + torch.arange(1 - to, 1), t_start)
        act_rows = (t.unsqueeze(1) + torch.arange(1 - to, h - to + 1)).clamp(min=t_start, max=t_last)
        return torch.cat([obs_rows, act_rows, t_start, t_last + 1], dim=1), {}

    def _empty(self) -> None:
        self._cache = None

    def state_dict(self) -> dict[str, Any]:
        return {}  # stateless: the randomness lives in the buffer's generator

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        return None

    def dumps(self, path) -> None:
        return None

    def loads(self, path) -> None:
        return None

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.layout})"


class ChunkStorage(LazyMemmapStorage):
    """A ``LazyMemmapStorage`` of steps that also reads chunk windows.

    ``get`` with a window index [B, To + H + 2] from :class:`ChunkWindowSampler` returns a [B]
    TensorDict: the observation key at the To observation rows ([B, To, ...]), ``chunk_key`` [B, H, A]
    with the padding rule applied, ``pad_key`` [B, H] (True on padded steps) and every other stored
    entry at the current step (``"episode"``, ``"step"``, ``("next", "reward")``, ...; not
    ``("next", "observation")``). With ``layout.rl_horizon`` the ``"next"`` entries are the chunk's
    instead (see :mod:`l1flow_rl.data.rl_windows`). Any other index reads rows.

    The episodes' metadata is kept once (``metadata``), not per row. ``alive`` (set by a writer that
    overwrites old episodes) marks the rows that still belong to a complete episode.
    """

    def __init__(self, max_size: int, *, layout: ChunkLayout, **kwargs) -> None:
        super().__init__(max_size, **kwargs)
        self.layout = layout
        self.metadata: EpisodeMetadata | None = None
        self.alive: Tensor | None = None
        self.revision = 0

    def loads(self, path) -> None:
        """TorchRL's ``loads``, and also into a larger storage than the one dumped (a fine-tune resumed
        with more ``online.steps``): the saved rows are copied to the front, the rest stay empty.
        TorchRL's checkpointer copies a dump only into a storage of its own size."""
        in_place = self.scratch_dir is not None and Path(self.scratch_dir).absolute() == Path(path).absolute()
        if in_place:  # TorchRL maps the files as they are (no copy)
            return super().loads(path)
        saved = TensorDict.load_memmap(path)
        rows = int(saved.shape[0])
        if rows == self.max_size:
            return super().loads(path)
        if rows > self.max_size:
            raise EpisodeDataError(
                f"{path}: the saved buffer holds {rows} rows, more than this buffer's {self.max_size}; a "
                "resumed run cannot keep fewer online steps than it stored"
            )
        length = int(json.loads((Path(path) / "storage_metadata.json").read_text())["len"])
        if not self.initialized:
            self._init(saved[0])
        self._storage[:rows].update_(saved)
        self._len = length
        self._bump_mutation_revision()
        return None

    def set(self, cursor, data, *, set_cursor: bool = True):
        if isinstance(data, TensorDictBase):
            data, meta = strip_metadata(data)
            if meta is not None:
                self.metadata = meta if self.metadata is None else merge_metadata([self.metadata, meta])
        return super().set(cursor, data, set_cursor=set_cursor)

    def get(self, index):
        if not self.layout.is_window_index(index):
            return super().get(index)
        lay = self.layout
        data: TensorDictBase = self._storage
        to, h = lay.obs_horizon, lay.pred_horizon
        obs_rows, act_rows = index[:, :to], index[:, to : to + h]
        start, end = index[:, to + h], index[:, to + h + 1]
        skip = [lay.observation_key, lay.action_key, next_key(lay.observation_key)]
        if lay.rl_horizon is not None:
            skip.append("next")  # replaced by the chunk's entries below
        out = _gather(data.exclude(*skip), obs_rows[:, -1])
        out.set(lay.observation_key, _gather(data.get(lay.observation_key), obs_rows))
        if lay.rl_horizon is not None:
            # a stand-in final observation (the file recorded none) must not be bootstrapped from
            final_known = self.metadata is None or self.metadata.has_final_observation is not False
            out.update(read_rl_targets(data, lay, obs_rows[:, -1], start, end, _gather, final_known))
        actions = _gather(data.get(lay.action_key), act_rows)
        col = torch.arange(lay.pred_horizon)
        current = lay.obs_horizon - 1
        same_as_next = torch.zeros_like(act_rows, dtype=torch.bool)
        same_as_next[:, :-1] = act_rows[:, :-1] == act_rows[:, 1:]
        same_as_prev = torch.zeros_like(act_rows, dtype=torch.bool)
        same_as_prev[:, 1:] = act_rows[:, 1:] == act_rows[:, :-1]
        # rows repeat only where clamped: the first row before the start, the last row after the end
        pad_before = same_as_next & (col < current)
        pad_after = same_as_prev & (col > current)
        if lay.action_pad == "delta":
            arm = lay.arm_mask(actions.shape[-1]).to(actions.device)
            actions = torch.where(
                pad_after.unsqueeze(-1) & arm, torch.zeros((), dtype=actions.dtype), actions
            )
        out.set(lay.chunk_key, actions)
        out.set(lay.pad_key, pad_before | pad_after)
        return out


def _gather(x: Tensor | TensorDictBase, rows: Tensor) -> Tensor | TensorDictBase:
    """``x[rows]`` for a row-index tensor of any shape.

    numpy's ``take`` copies on the calling thread with the GIL released (so prefetch threads overlap
    with training); torch's indexing kernels split the copy over the intra-op thread pool, which
    stalls when the cores are busy with training: several times slower on large image batches.
    """
    if isinstance(x, TensorDictBase):
        return x.apply(lambda leaf: _gather(leaf, rows), batch_size=rows.shape)
    flat = np.take(x.as_subclass(Tensor).numpy(), rows.reshape(-1).numpy(), axis=0)
    return torch.from_numpy(flat).reshape(*rows.shape, *x.shape[1:])
