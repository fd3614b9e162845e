"""Hand-made episodes whose every entry can be traced back to its episode and step (the RL buffer's
and the fine-tuning losses' tests compute their expected values from them)."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from l1flow_rl.data import attach_metadata
from l1flow_rl.data.episodes import assemble_episode

__all__ = ["GAMMA", "make_episodes"]

GAMMA = 0.9


def make_episodes(lengths=(6, 9), terminated=(True, False), final=True, **meta) -> TensorDict:
    """Episode e, step t: observation [e*1000 + t, -t], reward 1 + t + 10 e, final observation
    [e*1000 + L, -L] (a value no step has), so every read can be traced back."""
    parts = []
    for e, (n, term) in enumerate(zip(lengths, terminated)):
        t = torch.arange(n + 1, dtype=torch.float32)
        obs = torch.stack([e * 1000 + t, -t], -1)
        parts.append(
            assemble_episode(
                e,
                obs[:n],
                torch.randn(n, 3),
                reward=1 + torch.arange(n, dtype=torch.float32) + 10 * e,
                terminated=term,
                final_observation=obs[n] if final else None,
            )
        )
    eps = torch.cat(parts)
    return attach_metadata(
        eps, {"source": "hand.h5", "has_rewards": True, "has_final_observation": final, **meta}
    )
