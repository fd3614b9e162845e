"""The train job's chunk padding: the padded actions follow the control recorded in the data (checked
against task.control), the extent follows data.padding."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf
from test_data_formats import write_maniskill

from l1flow_rl.config import AppConfig
from l1flow_rl.data import EpisodeDataError, attach_metadata, episodes_metadata, load_episodes
from l1flow_rl.workspace.dataset import chunk_padding, make_train_buffer

TO, H, K = 2, 8, 4


def config(control="delta", padding="maniskill", **policy):
    cfg = OmegaConf.structured(AppConfig)
    cfg.task.control = control
    cfg.data.padding = padding
    cfg.policy.obs_horizon, cfg.policy.pred_horizon, cfg.policy.action_steps = TO, H, K
    for key, value in policy.items():
        cfg.policy[key] = value
    cfg.train.batch_size, cfg.train.prefetch = 2000, 0
    return cfg


@pytest.fixture
def delta_eps(tmp_path):
    write_maniskill(tmp_path / "demo.h5", lengths=(12, 15), control_mode="pd_ee_delta_pos")
    return load_episodes(tmp_path / "demo.h5")


def padded_after(batch):
    return batch["action_is_pad"] & (torch.arange(H) > TO - 1)


def test_padding_is_chosen_from_the_recorded_control_mode(delta_eps, tmp_path):
    assert episodes_metadata(delta_eps).control == "delta"  # from pd_ee_delta_pos
    batch = make_train_buffer(config("delta"), delta_eps, seed=0).sample()
    after = padded_after(batch)
    assert after.any()
    assert (batch["action_chunk"][after][:, :3] == 0).all() and (
        batch["action_chunk"][after][:, 3] != 0
    ).all()
    # a file recorded with an absolute controller pads by repeating the last action
    write_maniskill(tmp_path / "abs.h5", lengths=(12, 15), control_mode="pd_ee_pose")
    absolute = load_episodes(tmp_path / "abs.h5")
    assert episodes_metadata(absolute).control == "absolute"
    batch = make_train_buffer(config("absolute"), absolute, seed=0).sample()
    after = padded_after(batch)
    last = absolute["action"][(absolute["next", "done"][:, 0]).nonzero().squeeze(1)]
    assert torch.equal(
        batch["action_chunk"][after], last[batch["episode"]].unsqueeze(1).expand(-1, H, -1)[after]
    )


def test_a_mismatch_with_task_control_names_both(delta_eps, tmp_path):
    with pytest.raises(
        EpisodeDataError, match=r"demo\.h5: recorded with delta control .*task\.control is 'absolute'"
    ):
        make_train_buffer(config("absolute"), delta_eps, seed=0)
    # data that record no control take the task's
    unknown = attach_metadata(delta_eps.clone(), {"source": "mine.h5"})
    assert chunk_padding(config("absolute"), unknown)["action_pad"] == "repeat"
    assert chunk_padding(config("delta"), unknown)["action_pad"] == "delta"


def test_padding_extent_follows_data_padding(delta_eps):
    for padding, most_after in (("maniskill", H - TO), ("diffusion_policy", K - 1)):
        batch = make_train_buffer(config("delta", padding), delta_eps, seed=0).sample()
        assert int(padded_after(batch).sum(1).max()) == most_after, padding
        # To - 1 steps before the start under both rules
        assert int(batch["action_is_pad"][:, : TO - 1].sum(1).max()) == TO - 1
    with pytest.raises(ValueError, match=r"data\.padding must be one of"):
        chunk_padding(config("delta", "zeros"), delta_eps)
    with pytest.raises(
        ValueError, match=r"policy\.action_steps - 1 = 7 .*pred_horizon - policy\.obs_horizon = 6"
    ):
        chunk_padding(config("delta", "diffusion_policy", action_steps=8), delta_eps)
