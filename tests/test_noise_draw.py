"""The noise-draw benchmark's per-start split: which starts succeed under every draw, some, none."""

import pytest
import torch

from benchmarks.bench_noise_draw import per_start_split
from benchmarks.finetune_report import render_noise_draw


def test_per_start_split_counts_starts_and_the_split_expected_if_the_start_did_not_matter():
    # 4 starts over 2 draws: one always, two sometimes, one never; overall rate 4/8 = 0.5
    split = per_start_split({10: 2, 11: 1, 12: 1, 13: 0}, draws=2, rate=0.5)
    assert (split["always"], split["sometimes"], split["never"]) == (1, 2, 1)
    # independent starts at 0.5: P(always) = P(never) = 0.25
    assert split["expected_if_start_ignored"] == pytest.approx(
        {"always": 1.0, "sometimes": 2.0, "never": 1.0}
    )
    assert split["wins_per_start"] == {"10": 2, "11": 1, "12": 1, "13": 0}


def test_start_determined_outcomes_show_against_the_independent_split():
    split = per_start_split({s: (3 if s < 3 else 0) for s in range(10)}, draws=3, rate=0.3)
    assert (split["always"], split["sometimes"], split["never"]) == (3, 0, 7)
    assert split["expected_if_start_ignored"]["sometimes"] == pytest.approx(10 * (1 - 0.3**3 - 0.7**3))


def test_the_report_shows_the_split_and_reads_files_saved_before_it():
    data = {
        "checkpoint": "c.pt",
        "task": "t",
        "episodes": 4,
        "episode_seeds": {"first": 10, "episodes": 4},
        "rows": [{"noise_seed": 10, "success_once": 0.5}, {"noise_seed": 11, "success_once": 0.5}],
        "mean": 0.5,
        "std_over_noise_seeds": 0.0,
        "binomial_std_at_mean": 0.25,
    }
    assert "Per start" not in render_noise_draw(data)
    data["per_start"] = per_start_split({10: 2, 11: 1, 12: 1, 13: 0}, draws=2, rate=0.5)
    text = render_noise_draw(data)
    assert "| observed | 1 | 2 | 1 |" in text
    assert "| if success ignored the start | 1.0 | 2.0 | 1.0 |" in text
    assert "executed action" not in text
    data["action_noise"] = 0.1
    assert "Gaussian noise of std 0.1 on every executed action" in render_noise_draw(data)


def test_action_noise_perturbs_every_action_inside_the_bounds_and_keeps_the_executed_steps():
    from tensordict import TensorDict

    from benchmarks.bench_noise_draw import ActionNoise
    from l1flow_rl.modules.actor import L1FlowActor

    torch.manual_seed(0)
    actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32)).eval()
    low, high = torch.tensor([-1.0, -0.1]), torch.tensor([1.0, 0.1])
    noisy = ActionNoise(actor, sigma=0.5, low=low, high=high)
    assert noisy.policy.action_steps == actor.policy.action_steps
    obs = TensorDict({"observation": torch.randn(64, 2, 5)}, batch_size=[64])
    torch.manual_seed(1)
    clean = actor(obs.clone())["action_chunk"]
    torch.manual_seed(1)
    chunk = noisy(obs.clone())["action_chunk"]
    assert chunk.shape == clean.shape
    assert (chunk >= low).all() and (chunk <= high).all()
    # the narrow dim is mostly pinned to its bounds; the wide one moves by about sigma
    inside = (chunk[..., 0] > -1) & (chunk[..., 0] < 1) & (clean[..., 0].abs() < 0.5)
    assert 0.3 < (chunk - clean)[..., 0][inside].std() < 0.7


def test_chunk_noise_holds_one_offset_over_every_step_of_a_chunk():
    from tensordict import TensorDict

    from benchmarks.bench_noise_draw import ActionNoise
    from l1flow_rl.modules.actor import L1FlowActor

    torch.manual_seed(0)
    actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32)).eval()
    wide = torch.tensor([100.0, 100.0])  # bounds that never clamp: the offset shows whole
    noisy = ActionNoise(actor, sigma=0.5, low=-wide, high=wide, per="chunk")
    obs = TensorDict({"observation": torch.randn(8, 2, 5)}, batch_size=[8])
    torch.manual_seed(1)
    clean = actor(obs.clone())["action_chunk"]
    torch.manual_seed(1)
    offset = noisy(obs.clone())["action_chunk"] - clean  # [8, H, 2]
    torch.testing.assert_close(offset, offset[:, :1].expand_as(offset))
    assert offset[:, 0].std() > 0.2  # and it differs between chunks
