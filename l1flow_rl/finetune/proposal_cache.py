"""A frozen flow's best-of-N proposals, drawn once per observation and reused by every later update.

QC's backup draws N chunks from the flow's 2-NFE sampler at every next observation of every batch:
on 2 CPU cores that is 256 x N network calls per update, nearly all of an update's time
(``benchmarks/results/finetune_cost_*.json``). While the flow is frozen, the N proposals at a stored
state are a fixed sample of a fixed distribution, so each distinct observation's proposals are drawn
once and kept: a replay window is drawn hundreds of times over a run, its proposals once.

Observations are keyed by their content (a digest of their bytes), not by a buffer row, so the
demonstrations, the online buffer and the final observations of truncated episodes need no row
bookkeeping and an overwritten row can never return stale proposals. The noise of an observation's
draw comes from a generator seeded by its digest and ``seed``, and the unseen observations are drawn in
blocks of a fixed size (the last one padded): the network's batched kernels round differently at
other batch sizes (~1e-6 on the 1-D UNet, measured), so a resumed run (whose cache starts empty and
meets the observations in other batches) draws the same proposals bit for bit.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torch import Tensor

__all__ = ["ProposalCache"]

_SEED_MASK = (1 << 63) - 1  # torch.Generator.manual_seed takes a non-negative 64-bit int


class ProposalCache:
    """Memoised ``propose(obs, noise) -> [B, N, h, A]`` for a frozen flow, keyed by observation content.

    Args:
        propose: ``(read observations [B, To], noise [B, N, H, A]) -> proposals [B, N, h, A]``
            (what is kept: :class:`~l1flow_rl.QCLoss` keeps the critic's executed steps only).
        noise_shape: ``(N, H, A)``, one draw's noise per observation.
        seed: mixed into every observation's noise seed (runs with other seeds draw other proposals).
        block: observations per ``propose`` call (a fixed batch size keeps a draw independent of
            which other observations it was drawn with).

    :attr:`hits` and :attr:`misses` count looked-up observations; ``len(cache)`` the observations held.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> calls = []
        >>> def propose(obs, noise):
        ...     calls.append(obs.shape[0])
        ...     return noise[..., :4, :] + obs["state"][:, -1, :1, None, None]
        >>> cache = ProposalCache(propose, noise_shape=(3, 16, 2))
        >>> obs = TensorDict({"state": torch.arange(10.0).reshape(5, 2, 1)}, [5, 2])
        >>> first = cache(obs)
        >>> first.shape, calls  # one call: a block of 16 observations (the 5, padded)
        (torch.Size([5, 3, 4, 2]), [16])
        >>> torch.equal(cache(obs[[4, 0]]), first[[4, 0]]), calls  # no new flow call
        (True, [16])
    """

    def __init__(
        self,
        propose: Callable[[TensorDictBase, Tensor], Tensor],
        noise_shape: tuple[int, ...],
        seed: int = 0,
        block: int = 16,
    ) -> None:
        if block < 1:
            raise ValueError(f"block must be >= 1, got {block}")
        self.propose = propose
        self.block = int(block)
        self.noise_shape = tuple(int(n) for n in noise_shape)
        self.seed = int(seed)
        self._store: dict[bytes, Tensor] = {}
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._store)

    def clear(self) -> None:
        self._store.clear()

    @staticmethod
    def keys(obs: TensorDictBase) -> list[bytes]:
        """One digest per observation [B, To, ...]: every leaf's bytes, in sorted key order."""
        digests = [hashlib.blake2b(digest_size=16) for _ in range(obs.shape[0])]
        for key in sorted(obs.keys(include_nested=True, leaves_only=True), key=str):
            rows = obs.get(key).detach().reshape(obs.shape[0], -1).cpu().contiguous().numpy()
            for digest, row in zip(digests, rows, strict=True):
                digest.update(str(key).encode())
                digest.update(row.tobytes())
        return [d.digest() for d in digests]

    def noise(self, key: bytes) -> Tensor:
        """The standard-normal noise [N, H, A] of the observation with digest ``key``."""
        seed = (int.from_bytes(key[:8], "little") ^ self.seed) & _SEED_MASK
        generator = torch.Generator().manual_seed(seed)
        return torch.randn(self.noise_shape, generator=generator)

    @torch.no_grad()
    def __call__(self, obs: TensorDictBase, keys: list[bytes] | None = None) -> Tensor:
        """The proposals [B, N, h, A] of read observations [B, To]: drawn for the unseen ones only.
        ``keys``: the observations' digests where the caller already has them (:meth:`keys`)."""
        keys = self.keys(obs) if keys is None else keys
        new: dict[bytes, int] = {}  # first row of each unseen observation (a batch may repeat one)
        for i, key in enumerate(keys):
            if key not in self._store and key not in new:
                new[key] = i
        self.misses += len(new)
        self.hits += len(keys) - len(new)
        if new:
            unseen = list(new)
            padded = unseen + unseen[-1:] * (-len(unseen) % self.block)
            for start in range(0, len(padded), self.block):
                block = padded[start : start + self.block]
                rows = torch.tensor([new[k] for k in block], device=obs.device)
                noise = torch.stack([self.noise(k) for k in block]).to(obs.device)
                drawn = self.propose(obs[rows], noise)
                for key, proposals in zip(block, drawn.unbind(0), strict=True):
                    # a padding row repeats one already stored; clone: not a view pinning the block
                    self._store.setdefault(key, proposals.clone())
        return torch.stack([self._store[k] for k in keys])
