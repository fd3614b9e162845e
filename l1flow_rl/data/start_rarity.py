"""Window weights that make rarely-solved starts count: each window's episode is weighted by the inverse
of the success rate the collected episodes show near its start.

Measured on robosuite Can (``benchmarks/results/diagnose_can_mixed30c*.json``): the start's success falls
from 0.50 to 0.07 with the can's distance from its bin's centre, the collected episodes succeed a quarter
as often at the far starts, and filtered BC drawing successful windows uniformly re-teaches the near
starts (its gain sits at 6-12 cm; 12-30 cm, 44 of 100 test starts, did not move). Weighting a success by
``1 / p(success | start)`` gives every region of starts the mass it has among the starts, however
rarely it is solved.

The estimate ``p`` is the fraction of successes among the ``k`` collected episodes whose starts lie
nearest (Euclidean over the named dimensions of the episode's first state observation), floored at
``1/k`` so that a start with no nearby success weighs at most ``k``. Demonstrations are weighted by the
same collected-episode estimate (it is the current policy's success that is rare there, not the
expert's). Until ``k`` episodes have been collected every window weighs 1.

No TorchRL sampler does this: ``PrioritizedSampler`` weights by per-item priorities written from a loss,
not by a function of the stored episodes' starts.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.data.replay_buffers.storages import Storage

from l1flow_rl.data.episodes import EpisodeDataError, episode_bounds

__all__ = ["StartRarity", "start_features"]


def start_features(data: TensorDictBase, rows: Tensor, dims: Sequence[int], source: str) -> Tensor:
    """The named dimensions of the state observation at ``rows`` ([R, len(dims)], float64)."""
    obs = data.get("observation")
    if isinstance(obs, TensorDictBase):
        if "state" not in obs:
            raise EpisodeDataError(
                f"{source}: task.start_dims index the state observation, but the stored observation has "
                f"no 'state' entry (has {sorted(map(str, obs.keys()))})"
            )
        obs = obs.get("state")
    obs = obs.reshape(obs.shape[0], -1)
    width = obs.shape[1]
    bad = [d for d in dims if not -width <= d < width]
    if bad:
        raise EpisodeDataError(
            f"{source}: task.start_dims {list(dims)} name dimensions {bad} outside the state observation's "
            f"{width}"
        )
    return obs[rows][:, list(dims)].double()


class StartRarity:
    """Per-anchor weights ``1 / p(success | start)`` from the episodes an online storage holds.

    Args:
        online: the online buffer's storage (collected episodes; read, never written).
        dims: state-observation dimensions that place an episode's start (``task.start_dims``).
        k: neighbours of the estimate (``online.start_rarity_k``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage
        >>> from l1flow_rl.data.start_rarity import StartRarity
        >>> # four collected episodes of 2 steps: starts at x = 0, 0.1 (both succeeded), 1.0, 1.1 (one did)
        >>> obs = torch.tensor([[0.0], [0.0], [0.1], [0.1], [1.0], [1.0], [1.1], [1.1]])
        >>> terminated = torch.tensor([0, 1, 0, 1, 0, 0, 0, 1]).bool()[:, None]
        >>> steps = TensorDict({"episode": torch.arange(4).repeat_interleave(2), "observation": obs,
        ...                     ("next", "terminated"): terminated}, batch_size=[8])
        >>> storage = LazyTensorStorage(8)
        >>> storage.set(range(8), steps)
        >>> rarity = StartRarity(storage, dims=[0], k=2)
        >>> rarity.weights(steps[torch.tensor([0, 6])], source="demo").tolist()  # starts at x=0 and x=1.1
        [1.0, 2.0]
    """

    def __init__(self, online: Storage, dims: Sequence[int], k: int) -> None:
        if k < 1:
            raise ValueError(f"online.start_rarity_k={k}: expected a positive neighbour count")
        if not dims:
            raise ValueError(
                "online.start_rarity_k > 0 needs task.start_dims (the observation dims of a start)"
            )
        self.online, self.dims, self.k = online, [int(d) for d in dims], int(k)
        self._table: tuple[Any, Tensor, Tensor] | None = None

    def _collected(self) -> tuple[Tensor, Tensor]:
        """Start features [E, D] and success [E] of the collected episodes, cached per storage state."""
        storage, key = self.online, self.revision
        if self._table is None or self._table[0] != key:
            feats = torch.zeros(0, len(self.dims), dtype=torch.float64)
            success = torch.zeros(0, dtype=torch.bool)
            if len(storage) > 0:
                data = storage.get(slice(None))
                start, end = episode_bounds(data.get("episode"), "online buffer")
                first = start.unique()
                alive = getattr(storage, "alive", None)
                if alive is not None:  # rows of overwritten episodes are gone
                    first = first[alive[first]]
                last = end[first] - 1
                terminated = data.get(("next", "terminated")).reshape(data.shape[0], -1)[:, 0].bool()
                feats = start_features(data, first, self.dims, "online buffer")
                success = terminated[last]
            self._table = (key, feats, success)
        return self._table[1], self._table[2]

    @property
    def revision(self) -> Any:
        """Changes whenever the collected episodes do (samplers cache their weights on it)."""
        storage = self.online
        return (
            len(storage),
            int(getattr(storage, "_mutation_revision", 0)),
            int(getattr(storage, "revision", 0)),
        )

    def weights(self, starts: TensorDictBase, source: str) -> Tensor:
        """Weights [R] of the episodes whose first steps are ``starts`` ([R] rows; 1 each until ``k``
        episodes have been collected)."""
        feats, success = self._collected()
        if success.numel() < self.k:
            return torch.ones(starts.shape[0], dtype=torch.float64)
        query = start_features(starts, torch.arange(starts.shape[0]), self.dims, source)
        nearest = torch.cdist(query, feats).topk(self.k, dim=1, largest=False).indices
        rate = success[nearest].double().mean(1).clamp(min=1.0 / self.k)
        return 1.0 / rate
