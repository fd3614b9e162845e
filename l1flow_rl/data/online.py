"""Online data into the chunk storage: TorchRL collector batches and whole episodes, kept contiguous.

A chunk window reads rows around its current step, so every episode must sit in the storage as one
run of rows. A collector hands out [n_envs, T] batches in which an episode may start in one batch
and end in a later one. :class:`CollectorEpisodes` holds each env's unfinished episode and releases
it when it ends; :class:`EpisodeWriter` writes complete episodes into a ring of rows, and when the
ring wraps, the episodes it overwrites (even partly) leave the sampling table whole.

    rb = make_chunk_buffer(demos, capacity=200_000, rl_horizon=5, gamma=0.99)   # writable
    for batch in collector:                    # ("next", ...) keys, ("collector", "traj_ids")
        rb.extend(batch)                       # finished episodes are stored, the rest is held
        sample = rb.sample()

TorchRL's ``RoundRobinWriter`` writes rows one by one and would split episodes across the wrap and
let windows read half-overwritten episodes; ``SliceSampler`` tolerates that but pads only at the
end. Hence this writer.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.data.replay_buffers.writers import Writer

from l1flow_rl.data.episodes import EpisodeDataError
from l1flow_rl.data.metadata import EpisodeMetadata, strip_metadata

__all__ = ["CORE_KEYS", "CollectorEpisodes", "EpisodeWriter"]

#: The entries every stored step has (demonstrations and online data alike).
CORE_KEYS: tuple[NestedKey, ...] = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
)
_TRAJ_KEY = ("collector", "traj_ids")


def _flag(data: TensorDictBase, key: NestedKey) -> Tensor:
    return data.get(key).reshape(*data.shape).bool()


@dataclass
class _Piece:
    """Steps of one env's unfinished episode; ``origin`` is (batch number, env, first step)."""

    steps: TensorDictBase
    origin: tuple[int, int, int]


@dataclass
class _Open:
    traj: int | None
    pieces: list[_Piece] = field(default_factory=list)


class CollectorEpisodes:
    """Cuts collector batches into complete episodes, holding each env's unfinished one.

    An episode ends at a step with ``("next", "done")``. A change of ``("collector", "traj_ids")``
    without a done (the collector reset the env) ends the held steps as a truncated episode: the
    observation after their last action is their last ``("next", "observation")``.

    Args:
        keys: the entries kept per step (default :data:`CORE_KEYS`); ``("next", "truncated")`` is
            derived (done and not terminated) when the env does not write it.
    """

    def __init__(self, keys: Sequence[NestedKey] = CORE_KEYS) -> None:
        self.keys = tuple(keys)
        self._open: dict[int, _Open] = {}
        self._batches = 0

    @property
    def pending_steps(self) -> int:
        """Steps held in unfinished episodes."""
        return sum(p.steps.shape[0] for o in self._open.values() for p in o.pieces)

    def _select(self, rows: TensorDictBase) -> TensorDictBase:
        keys = rows.keys(include_nested=True)
        if (
            ("next", "truncated") in self.keys
            and ("next", "truncated") not in keys
            and ("next", "done") in keys
        ):
            rows = rows.clone(False)
            rows.set(("next", "truncated"), rows.get(("next", "done")) & ~rows.get(("next", "terminated")))
        missing = [k for k in self.keys if k not in rows.keys(include_nested=True)]
        if missing:
            raise KeyError(
                f"collector data lack {missing} (has {sorted(map(str, rows.keys(True, True)))}); an env "
                "for online data must write the observation, the action and the ('next', ...) entries"
            )
        return rows.select(*self.keys)

    def add(self, batch: TensorDictBase) -> list[tuple[TensorDictBase, list[tuple[int, int, int, int]]]]:
        """The episodes ``batch`` completes: (steps [L], [(batch number, env, first, last+1), ...])."""
        if batch.batch_dims == 1:
            batch = batch.unsqueeze(0)
        if batch.batch_dims != 2:
            raise ValueError(
                f"expected collector data [n_envs, T] or [T], got batch size {tuple(batch.shape)}"
            )
        serial = self._batches
        self._batches += 1
        done = _flag(batch, ("next", "done")).tolist()  # Python lists: the loop below reads every step
        traj = batch.get(_TRAJ_KEY).reshape(*batch.shape).tolist() if _TRAJ_KEY in batch.keys(True) else None
        steps = self._select(batch)
        finished = []
        for env in range(batch.shape[0]):
            held = self._open.get(env) or _Open(traj=None)
            first = 0
            for t in range(batch.shape[1]):
                this_traj = None if traj is None else traj[env][t]
                if this_traj is not None and held.traj is not None and this_traj != held.traj:
                    # the collector reset the env without a done: what came before ends truncated
                    if t > first:
                        held.pieces.append(_Piece(steps[env, first:t], (serial, env, first)))
                    if held.pieces:
                        finished.append(self._close(held, truncate=True))
                    held, first = _Open(traj=None), t
                if held.traj is None:
                    held.traj = this_traj
                if done[env][t]:
                    held.pieces.append(_Piece(steps[env, first : t + 1], (serial, env, first)))
                    finished.append(self._close(held, truncate=False))
                    held, first = _Open(traj=None), t + 1
            if first < batch.shape[1]:
                # a copy: collectors may reuse their output's memory for the next batch
                held.pieces.append(_Piece(steps[env, first:].clone(), (serial, env, first)))
            self._open[env] = held
        return finished

    def flush(self) -> list[tuple[TensorDictBase, list[tuple[int, int, int, int]]]]:
        """Every held episode, ended as truncated (e.g. when collection stops)."""
        out = [self._close(o, truncate=True) for o in self._open.values() if o.pieces]
        self._open.clear()
        return out

    def _close(self, held: _Open, *, truncate: bool):
        steps = torch.cat([p.steps for p in held.pieces], 0) if len(held.pieces) > 1 else held.pieces[0].steps
        if truncate:
            # new tensors, not writes into get()'s result: a lazily stacked batch returns a fresh copy
            steps = steps.clone(False)
            done = steps.get(("next", "done")).clone()
            done[-1] = True
            truncated = steps.get(("next", "truncated")).clone()
            truncated[-1] = ~steps.get(("next", "terminated"))[-1]
            steps.set(("next", "done"), done)
            steps.set(("next", "truncated"), truncated)
        spans = [(*p.origin, p.origin[2] + p.steps.shape[0]) for p in held.pieces]
        return steps, spans


class EpisodeWriter(Writer):
    """Writes complete episodes as contiguous runs into a ring of storage rows.

    ``extend`` takes either collector batches ([n_envs, T] or [T] with ``("next", "done")``; unfinished
    episodes are held, see :class:`CollectorEpisodes`) or steps of complete episodes in the layout of
    :mod:`l1flow_rl.data.episodes` (every ``"episode"`` run ending with a done step). Each stored
    episode gets a fresh ``"episode"`` id and its ``"step"`` column; only ``keys`` are stored, so
    demonstrations and online data share one set of entries. An episode that does not fit before the
    ring's end starts again at row 0; the episodes it overwrites leave the sampling table.

    Args:
        keys: the entries stored per step besides ``"episode"`` and ``"step"``.
        require_rewards: refuse episodes whose metadata says they carry no rewards (RL buffers).
    """

    def __init__(self, keys: Sequence[NestedKey] = CORE_KEYS, *, require_rewards: bool = False) -> None:
        super().__init__()
        self.keys = tuple(keys)
        self.require_rewards = require_rewards
        self.collector = CollectorEpisodes(self.keys)
        self._cursor = 0
        self._high = 0  # rows below this have been written
        self._next_id = 0
        self._live: dict[int, tuple[int, int]] = {}  # episode id -> (first row, end row)

    # -- writing -------------------------------------------------------------------------------
    def add(self, data: Any) -> int:
        raise RuntimeError(
            "an episode buffer stores whole episodes: use extend() with collector batches or episodes"
        )

    def extend(self, data: TensorDictBase) -> Tensor:
        if not isinstance(data, TensorDictBase):
            raise TypeError(f"expected a TensorDict, got {type(data).__name__}")
        data, meta = strip_metadata(data)
        if self.require_rewards and meta is not None and meta.has_rewards is False:
            raise EpisodeDataError(
                f"{meta.describe()}: records no rewards, so it cannot feed an RL buffer (replay the "
                "demonstrations with rewards, or pick another reward key)"
            )
        if meta is not None and self._storage.metadata is None:
            self._storage.metadata = meta
        index = torch.full(data.shape, -1, dtype=torch.long)
        if data.batch_dims == 2 or _TRAJ_KEY in data.keys(True):
            for steps, spans in self.collector.add(data):
                rows = self._write(steps)
                offset = 0
                for serial, env, first, stop in spans:
                    if serial == self.collector._batches - 1:  # steps of this very batch
                        n = stop - first
                        where = index if index.dim() == 2 else index.unsqueeze(0)
                        where[env, first:stop] = rows[offset : offset + n]
                    offset += stop - first
            return index
        for steps, lo, hi in self._complete_episodes(data):
            index[lo:hi] = self._write(steps)
        return index

    def flush(self) -> int:
        """Store every held unfinished collector episode as truncated; returns the steps stored."""
        total = 0
        for steps, _ in self.collector.flush():
            self._write(steps)
            total += steps.shape[0]
        return total

    def _complete_episodes(self, data: TensorDictBase):
        if data.batch_dims != 1 or "episode" not in data.keys():  # noqa: SIM118
            raise ValueError(
                "extend() takes collector batches ([n_envs, T] with ('next', 'done')) or episode steps "
                f"[N] with an 'episode' column; got batch size {tuple(data.shape)}, keys "
                f"{sorted(map(str, data.keys()))}"
            )
        ids, counts = torch.unique_consecutive(data.get("episode").reshape(-1), return_counts=True)
        done = _flag(data, ("next", "done"))
        lo = 0
        for e, n in zip(ids.tolist(), counts.tolist()):
            hi = lo + n
            if not bool(done[hi - 1]):
                raise EpisodeDataError(
                    f"episode {e}: its last step has no ('next', 'done'); only complete episodes can be "
                    "stored (collector batches keep unfinished ones until they end)"
                )
            missing = [k for k in self.keys if k not in data.keys(include_nested=True)]
            if missing:
                raise KeyError(f"episodes lack {missing} (has {sorted(map(str, data.keys(True, True)))})")
            yield data[lo:hi].select(*self.keys), lo, hi
            lo = hi

    def _write(self, steps: TensorDictBase) -> Tensor:
        storage = self._storage
        n, capacity = steps.shape[0], storage.max_size
        if n > capacity:
            raise EpisodeDataError(f"an episode of {n} steps does not fit in a buffer of {capacity} rows")
        if self._cursor + n > capacity:
            self._cursor = 0
        lo, hi = self._cursor, self._cursor + n
        for e, (a, b) in list(self._live.items()):
            if a < hi and lo < b:  # overwritten, even partly: the rest of it is dead
                storage.alive[a:b] = False
                del self._live[e]
        episode = self._next_id
        self._next_id += 1
        steps = steps.clone(False)
        steps.set("episode", torch.full((n,), episode, dtype=torch.long))
        steps.set("step", torch.arange(n))
        rows = torch.arange(lo, hi)
        storage.set(rows, steps, set_cursor=False)  # the length is the ring's high-water mark, below
        storage._set_last_cursor(rows)  # what TorchRL's storage checkpointer reads on dumps()
        if storage.alive is None or storage.alive.numel() != capacity:
            storage.alive = torch.zeros(capacity, dtype=torch.bool)
        storage.alive[lo:hi] = True
        self._live[episode] = (lo, hi)
        self._cursor = hi
        self._high = max(self._high, hi)
        storage._len = self._high
        storage.revision += 1
        return rows

    # -- bookkeeping -----------------------------------------------------------------------------
    def _empty(self, empty_write_count: bool = True) -> None:
        self._cursor = self._high = 0
        self._live.clear()
        self.collector = CollectorEpisodes(self.keys)
        if self._storage is not None and self._storage.alive is not None:
            self._storage.alive.zero_()
            self._storage.revision += 1

    def state_dict(self) -> dict[str, Any]:
        """The ring's bookkeeping. Unfinished collector episodes are not kept: a resumed collector
        starts its episodes afresh."""
        alive = self._storage.alive if self._storage is not None else None
        return {
            "cursor": self._cursor,
            "high": self._high,
            "next_id": self._next_id,
            "live": torch.tensor([[e, a, b] for e, (a, b) in self._live.items()], dtype=torch.long).reshape(
                -1, 3
            ),
            "alive": alive.clone() if alive is not None else torch.zeros(0, dtype=torch.bool),
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._cursor, self._high = int(state_dict["cursor"]), int(state_dict["high"])
        self._next_id = int(state_dict["next_id"])
        self._live = {int(e): (int(a), int(b)) for e, a, b in state_dict["live"].tolist()}
        self.collector = CollectorEpisodes(self.keys)
        if self._storage is not None:
            alive = state_dict["alive"].clone() if state_dict["alive"].numel() else None
            grown = None if alive is None else self._storage.max_size - alive.numel()
            if grown:  # a storage larger than the dumped one (a resumed run given more steps): rows unused
                alive = torch.cat([alive, alive.new_zeros(grown)])
            self._storage.alive = alive
            self._storage._len = self._high
            self._storage.revision += 1

    def dumps(self, path) -> None:
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        torch.save(self.state_dict(), path / "episode_writer.pt")
        meta = self._storage.metadata if self._storage is not None else None
        (path / "episode_writer.json").write_text(json.dumps({"metadata": meta.to_json() if meta else None}))

    def loads(self, path) -> None:
        path = Path(path)
        self.load_state_dict(torch.load(path / "episode_writer.pt", weights_only=True))
        meta = json.loads((path / "episode_writer.json").read_text())["metadata"]
        if self._storage is not None and meta:
            self._storage.metadata = EpisodeMetadata.from_json(meta)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(episodes={len(self._live)}, cursor={self._cursor}, keys={self.keys})"
