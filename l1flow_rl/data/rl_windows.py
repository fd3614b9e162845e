"""What a chunked critic reads from a window (QC-FQL's targets), computed from the stored steps.

For a window whose current step is t in an episode of length L, with h = ``rl_horizon`` executed
actions (``action_chunk[:, To-1 : To-1+h]``) and discount g:

============================ ==========================================================================
``("next", "reward")``       [B, 1] sum_{i=0}^{min(h, L-t)-1} g^i r_{t+i}, the discounted chunk return
``("next", "observation")``  [B, To, ...] the history-stacked observation at step t+h: steps
                             t+h-To+1 ... t+h, each clamped to [0, L]; step L is the final observation
                             (``("next", "observation")`` of the last step), so t+h > L reads it too
``("next", "done")``         [B, 1] t+h >= L (the chunk reaches the episode's end)
``("next", "terminated")``   [B, 1] done and the episode ended in a terminal state
``("next", "truncated")``    [B, 1] done and not terminated
``"chunk_valid"``            [B, 1] t+h <= L (all h executed actions lie inside the episode), or the
                             episode terminated: a chunk that crosses a terminal end keeps its
                             return summed to that end and needs no bootstrap. Data without a
                             recorded final observation also mark invalid the window with t+h == L
                             of a truncated episode, whose bootstrap would need it
============================ ==========================================================================

The TD target is then ``R + g^h * (1 - terminated) * Q(next observation, next chunk)``, masked by
``chunk_valid`` (:class:`~l1flow_rl.ChunkCriticLoss`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor

if TYPE_CHECKING:  # pragma: no cover
    from l1flow_rl.data.chunks import ChunkLayout

__all__ = ["next_key", "read_rl_targets"]


def next_key(key: NestedKey) -> tuple[str, ...]:
    """``("next", *key)``."""
    return ("next", *((key,) if isinstance(key, str) else tuple(key)))


def _where_rows(mask: Tensor, a, b):
    """``a`` where ``mask`` [B, To] else ``b``, for tensors or TensorDicts of [B, To, ...] leaves."""
    if isinstance(a, TensorDictBase):
        return a.apply(lambda x, y: _where_rows(mask, x, y), b)
    return torch.where(mask.reshape(*mask.shape, *(1,) * (a.dim() - mask.dim())), a, b)


def read_rl_targets(
    data: TensorDictBase,
    layout: ChunkLayout,
    t: Tensor,
    start: Tensor,
    end: Tensor,
    gather: Callable,
    final_observation_known: bool = True,
) -> TensorDict:
    """The RL entries of B windows: current rows ``t``, episode rows ``[start, end)`` (all [B]).
    ``final_observation_known=False``: the stored final observations are stand-ins (see the table)."""
    h, to, gamma = int(layout.rl_horizon), layout.obs_horizon, float(layout.gamma)
    batch = t.shape[0]
    length = (end - start).unsqueeze(1)
    rel = (t - start).unsqueeze(1)  # the current step inside its episode

    # the discounted rewards of the chunk, h steps at most and none past the episode's end
    span = torch.arange(h)
    rows = torch.minimum(t.unsqueeze(1) + span, end.unsqueeze(1) - 1)
    rewards = gather(data.get(layout.reward_key), rows).reshape(batch, h).to(torch.float64)
    discounted = rewards * gamma ** span.to(torch.float64) * (rel + span < length)
    chunk_return = discounted.sum(1, keepdim=True).to(torch.float32)

    # the observation history at t+h; step L (and past it) is the final observation
    hist = (rel + h - to + 1 + torch.arange(to)).clamp(min=0)
    hist = torch.minimum(hist, length)
    at_end = hist == length
    observations = gather(data.get(layout.observation_key), start.unsqueeze(1) + hist.clamp(max=length - 1))
    if bool(at_end.any()):
        # one final frame per window, broadcast over the history (a view, no copy per history step)
        final = gather(data.get(next_key(layout.observation_key)), (end - 1).unsqueeze(1))
        shape = (batch, to) if isinstance(final, TensorDictBase) else (batch, to, *final.shape[2:])
        final = final.expand(*shape)
        observations = _where_rows(at_end, final, observations)

    episode_terminated = gather(data.get(("next", "terminated")), end - 1).reshape(batch, 1).bool()
    done = rel + h >= length
    valid = (rel + h <= length) | episode_terminated
    if not final_observation_known:
        valid &= ~((rel + h == length) & ~episode_terminated)
    out = TensorDict(
        {
            "next": {
                "reward": chunk_return,
                "done": done,
                "terminated": done & episode_terminated,
                "truncated": done & ~episode_terminated,
            },
            "chunk_valid": valid,
        },
        batch_size=[batch],
    )
    out.set(next_key(layout.observation_key), observations)
    return out
