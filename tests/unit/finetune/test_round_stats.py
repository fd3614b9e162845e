"""A collection round's success figures: the share of ended episodes, and each env's first episode."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from l1flow_rl.finetune.collect import round_stats


def _round(done_at: list[list[int]], success_at: list[list[int]], steps: int = 6) -> TensorDict:
    done = torch.zeros(len(done_at), steps, 1, dtype=torch.bool)
    success = torch.zeros(len(done_at), steps, 1, dtype=torch.bool)
    for env, (ends, wins) in enumerate(zip(done_at, success_at)):
        done[env, ends] = True
        success[env, wins] = True
    nxt = {"done": done, "success": success, "reward": success.float()}
    return TensorDict({"next": TensorDict(nxt, [len(done_at), steps])}, [len(done_at), steps])


def test_the_first_episode_share_counts_each_env_once_whatever_its_outcome():
    """Env 0 succeeds at step 1, then again at step 3 (the second episode ends only because it
    succeeds), env 1 fails at the time limit (step 5): 2 of 3 ended episodes succeeded, but of the
    first episodes 1 of 2."""
    stats = round_stats(_round([[1, 3], [5]], [[1, 3], []]))
    assert stats["episodes_ended"] == 3 and stats["episodes_succeeded"] == 2
    assert stats["episode_success"] == pytest.approx(2 / 3)
    assert stats["first_episodes"] == 2 and stats["first_episode_success"] == 0.5


def test_an_env_whose_episode_the_round_cuts_has_no_first_episode():
    stats = round_stats(_round([[2], []], [[], []]))
    assert stats["first_episodes"] == 1 and stats["first_episode_success"] == 0.0
    assert round_stats(_round([[], []], [[], []]))["first_episode_success"] is None
