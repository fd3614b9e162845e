"""``l1flow-rl train task=pusht`` end to end on the real gym-pusht simulator, with tiny budgets:
scripted demonstrations, training, and an evaluation that reports Diffusion Policy's score."""

from __future__ import annotations

import json

import pytest

from l1flow_rl.commands.cli import main

pytest.importorskip("gym_pusht", reason="needs gym-pusht: pip install 'l1flow-rl[pusht]'")
pytestmark = pytest.mark.pusht

TINY = [
    "task=pusht",
    "demos.num=3",
    "train.steps=20",
    "eval.episodes=1",
    "eval.num_envs=1",
    "train.batch_size=16",
    "network.down_dims=[16,32]",
    "network.timestep_embed_dim=16",
]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("pusht_data")


def test_train_pusht_end_to_end(tmp_path, data_dir):
    run_dir = tmp_path / "run"
    assert main(["train", f"data_dir={data_dir}", f"run_dir={run_dir}", *TINY]) == 0
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["episodes"] == 1
    episode = result["per_episode"][0]
    assert 0.0 <= episode["score"] <= 1.0 and 0.0 <= episode["max_coverage"] <= 1.0
    # the score is the best clip(coverage / 0.95, 0, 1) of the episode
    assert episode["score"] == pytest.approx(min(1.0, episode["max_coverage"] / 0.95), abs=1e-5)
    assert (data_dir / "pusht" / "pusht_lowdim_n3_seed0.zarr").is_dir()


def test_diffusion_policy_protocol_sets_seeds_steps_and_headline(tmp_path, data_dir):
    run_dir = tmp_path / "run"
    args = [*TINY, "eval.protocol=diffusion_policy", "eval.episodes=1", "train.steps=2"]
    assert main(["train", f"data_dir={data_dir}", f"run_dir={run_dir}", *args]) == 0
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["protocol"]["name"] == "diffusion_policy"
    assert result["headline"]["metric"] == "score"
    assert result["seeds"][0] == 100000
    assert result["protocol"]["max_episode_steps"] == 300
