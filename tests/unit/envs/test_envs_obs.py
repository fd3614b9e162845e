"""flatten_maniskill_obs: layout, dtypes and errors on hand-built observation dicts (no simulator)."""

import numpy as np
import pytest
import torch
from l1flow_rl.envs.maniskill.obs import flatten_maniskill_obs


def _obs(*batch: int) -> dict:
    return {
        "agent": {"qpos": torch.arange(9.0).expand(*batch, 9), "qvel": torch.full((*batch, 9), -1.0)},
        "extra": {
            "is_grasped": torch.ones(batch, dtype=torch.bool),
            "tcp_pose": torch.full((*batch, 7), 2.0),
        },
        "sensor_param": {"base_camera": {"intrinsic_cv": torch.zeros(*batch, 3, 3)}},
        "sensor_data": {"base_camera": {"rgb": torch.randint(0, 255, (*batch, 8, 6, 3), dtype=torch.uint8)}},
    }


def test_state_is_agent_then_extra_in_key_order_and_rgb_is_channels_first():
    obs = _obs(4)
    out = flatten_maniskill_obs(obs)
    assert out["state"].dtype == torch.float32 and out["state"].shape == (4, 26)
    expected_row = torch.cat(
        [torch.arange(9.0), torch.full((9,), -1.0), torch.ones(1), torch.full((7,), 2.0)]
    )
    assert torch.equal(out["state"], expected_row.expand(4, 26))
    assert out["rgb"].dtype == torch.uint8 and out["rgb"].shape == (4, 3, 8, 6)
    assert torch.equal(out["rgb"], obs["sensor_data"]["base_camera"]["rgb"].permute(0, 3, 1, 2))


def test_any_leading_dims_and_numpy_leaves():
    obs = _obs(5, 2)
    as_numpy = {g: {k: v.numpy() for k, v in obs[g].items()} for g in ("agent", "extra")}
    out = flatten_maniskill_obs(as_numpy)
    assert set(out) == {"state"} and out["state"].shape == (5, 2, 26)
    assert torch.equal(out["state"], flatten_maniskill_obs(obs)["state"])
    single = {g: {k: v[0, 0] for k, v in as_numpy[g].items()} for g in ("agent", "extra")}
    assert torch.equal(flatten_maniskill_obs(single)["state"], out["state"][0, 0])
    assert isinstance(as_numpy["extra"]["is_grasped"], np.ndarray)


def test_errors_name_the_problem():
    with pytest.raises(KeyError, match="lacks \\['extra'\\]"):
        flatten_maniskill_obs({"agent": {"qpos": torch.zeros(1, 9)}})
    obs = _obs(3)
    obs["extra"]["tcp_pose"] = torch.zeros(2, 7)
    with pytest.raises(ValueError, match="extra/tcp_pose"):
        flatten_maniskill_obs(obs)
    obs = _obs(3)
    obs["sensor_data"]["hand_camera"] = obs["sensor_data"]["base_camera"]
    with pytest.raises(ValueError, match="pass camera="):
        flatten_maniskill_obs(obs)
    assert flatten_maniskill_obs(obs, camera="hand_camera")["rgb"].shape == (3, 3, 8, 6)
    obs["sensor_data"]["base_camera"] = {"rgb": torch.zeros(3, 8, 6, 3)}
    with pytest.raises(TypeError, match="uint8"):
        flatten_maniskill_obs(obs, camera="base_camera")
