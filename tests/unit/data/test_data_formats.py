"""Importers on small files written here in each format, and the bad-input errors."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from l1flow_rl.data import EpisodeDataError, episodes_metadata, load_episodes, make_chunk_buffer

RNG = np.random.default_rng(0)


# -- writers ---------------------------------------------------------------------------------
def write_maniskill(path, lengths=(5, 8), control_mode="pd_ee_delta_pos", rgb=False, rewards=True):
    episodes, data = [], {}
    with h5py.File(path, "w") as f:
        for i, n in enumerate(lengths):
            g = f.create_group(f"traj_{i}", track_order=True)
            if rgb:
                obs = g.create_group("obs", track_order=True)
                agent = obs.create_group("agent", track_order=True)
                agent["qpos"] = RNG.normal(size=(n + 1, 9)).astype(np.float32)
                agent["qvel"] = RNG.normal(size=(n + 1, 9)).astype(np.float32)
                extra = obs.create_group("extra", track_order=True)
                extra["tcp_pose"] = RNG.normal(size=(n + 1, 7)).astype(
                    np.float32
                )  # not in name order on purpose
                extra["goal_pos"] = RNG.normal(size=(n + 1, 3)).astype(np.float32)
                obs["sensor_param/base_camera/intrinsic_cv"] = np.zeros((n + 1, 3, 3), np.float32)
                obs["sensor_data/base_camera/rgb"] = RNG.integers(0, 255, (n + 1, 6, 7, 3), dtype=np.uint8)
            else:
                g["obs"] = RNG.normal(size=(n + 1, 6)).astype(np.float32)
            g["actions"] = RNG.uniform(-1, 1, size=(n, 4)).astype(np.float32)
            success = np.arange(n) >= n - 2
            g["success"], g["terminated"], g["truncated"] = success, success, np.zeros(n, bool)
            if rewards:
                g["rewards"] = RNG.uniform(size=n).astype(np.float32)
            data[i] = {k: g[k][()] for k in g if isinstance(g[k], h5py.Dataset)}
            episodes.append(
                {"episode_id": i, "episode_seed": i, "control_mode": control_mode, "elapsed_steps": n}
            )
    meta = {
        "env_info": {
            "env_id": "PushCube-v1",
            "env_kwargs": {"control_mode": control_mode, "obs_mode": "state"},
        },
        "episodes": episodes,
    }
    path.with_suffix(".json").write_text(json.dumps(meta))
    return data


def write_robomimic(path, lengths=(4, 6), image=True):
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = json.dumps({"env_name": "Lift", "type": 1})
        for i, n in enumerate(lengths):
            g = data.create_group(f"demo_{i}")
            g["obs/robot0_eef_pos"] = RNG.normal(size=(n, 3))
            g["obs/object"] = RNG.normal(size=(n, 10))
            if image:
                g["obs/agentview_image"] = RNG.integers(0, 255, (n, 8, 8, 3), dtype=np.uint8)
            g["actions"] = RNG.uniform(-1, 1, (n, 7))
            g["rewards"] = np.arange(n) == n - 1
            g["dones"] = (np.arange(n) == n - 1).astype(np.int64)


def write_dp_zarr(path, lengths=(3, 5), zarr_format=3, img=True):
    import zarr

    total = sum(lengths)
    root = zarr.open_group(str(path), mode="w", zarr_format=zarr_format)
    data = root.create_group("data")
    data.create_array("state", data=RNG.uniform(0, 512, (total, 5)).astype(np.float32))
    data.create_array("action", data=RNG.uniform(0, 512, (total, 2)).astype(np.float32))
    if img:  # Diffusion Policy stores whole values 0..255 as float32
        data.create_array("img", data=RNG.integers(0, 256, (total, 4, 4, 3)).astype(np.float32))
    root.create_group("meta").create_array("episode_ends", data=np.cumsum(lengths).astype(np.int64))
    return root


# -- importers -------------------------------------------------------------------------------
def test_maniskill_state_file(tmp_path):
    path = tmp_path / "demo.h5"
    raw = write_maniskill(path)
    eps = load_episodes(path, control_mode="pd_ee_delta_pos")
    assert eps.shape == (13,) and eps["observation"].shape == (13, 6)
    assert eps["episode"].tolist() == [0] * 5 + [1] * 8 and eps["step"].tolist() == [*range(5), *range(8)]
    np.testing.assert_array_equal(eps["observation"][5:].numpy(), raw[1]["obs"][:8])
    # the observation after each action, the T+1st (final) one included
    np.testing.assert_array_equal(eps["next", "observation"][5:].numpy(), raw[1]["obs"][1:9])
    np.testing.assert_array_equal(eps["next", "observation"][4].numpy(), raw[0]["obs"][5])
    np.testing.assert_array_equal(eps["action"][:5].numpy(), raw[0]["actions"])
    np.testing.assert_array_equal(eps["next", "reward"][:5, 0].numpy(), raw[0]["rewards"])
    np.testing.assert_array_equal(
        eps["next", "sparse_reward"][:5, 0].numpy(), raw[0]["success"].astype(np.float32)
    )
    assert eps["next", "done"][:, 0].nonzero().squeeze(1).tolist() == [4, 12]
    assert eps["next", "terminated"][[4, 12], 0].all() and not eps["next", "truncated"].any()
    meta = episodes_metadata(eps)
    assert (meta.format, meta.env_id, meta.control_mode, meta.control) == (
        "maniskill",
        "PushCube-v1",
        "pd_ee_delta_pos",
        "delta",
    )
    assert meta.source == str(path) and meta.has_rewards and meta.has_final_observation
    # a delta-control file pads chunks with zero arm motion by default
    batch = make_chunk_buffer(eps, obs_horizon=2, pred_horizon=8, batch_size=200, seed=0).sample()
    padded_after = batch["action_is_pad"] & (torch.arange(8) > 1)
    assert padded_after.any()
    assert (batch["action_chunk"][padded_after][:, :3] == 0).all()
    assert (batch["action_chunk"][padded_after][:, 3] != 0).all()


def test_maniskill_rgb_file_is_flattened_like_the_live_env(tmp_path):
    path = tmp_path / "demo.rgb.h5"
    write_maniskill(path, rgb=True, rewards=False)
    eps = load_episodes(path)
    obs = eps["observation"]
    assert obs["state"].shape == (13, 9 + 9 + 7 + 3) and obs["rgb"].shape == (13, 3, 6, 7)
    with h5py.File(path) as f:
        g = f["traj_1/obs"]
        expected = np.concatenate(
            [g["agent/qpos"], g["agent/qvel"], g["extra/tcp_pose"], g["extra/goal_pos"]], -1
        )
        np.testing.assert_array_equal(obs["state"][5:].numpy(), expected[:8])
        np.testing.assert_array_equal(
            obs["rgb"][5:].numpy(), g["sensor_data/base_camera/rgb"][:8].transpose(0, 3, 1, 2)
        )
        # the final (T+1st) frame and state are the observation after the last action
        np.testing.assert_array_equal(
            eps["next", "observation", "rgb"][12].numpy(),
            g["sensor_data/base_camera/rgb"][8].transpose(2, 0, 1),
        )
        np.testing.assert_array_equal(eps["next", "observation", "state"][12].numpy(), expected[8])
    # without recorded rewards the reward is the sparse one, and the metadata says none was recorded
    assert torch.equal(eps["next", "reward"], eps["next", "sparse_reward"])
    assert episodes_metadata(eps).has_rewards is False
    with pytest.raises(EpisodeDataError, match=r"demo\.rgb\.h5: records no rewards"):
        make_chunk_buffer(eps, obs_horizon=2, pred_horizon=4, rl_horizon=2)
    batch = make_chunk_buffer(
        eps, obs_horizon=2, pred_horizon=4, batch_size=8, rl_horizon=2, reward_key=("next", "sparse_reward")
    ).sample()
    assert batch["next", "observation", "rgb"].shape == (8, 2, 3, 6, 7)


@pytest.mark.parametrize("image", [True, False])
def test_robomimic_file(tmp_path, image):
    path = tmp_path / "lift.hdf5"
    write_robomimic(path, image=image)
    eps = load_episodes(path)
    with h5py.File(path) as f:
        demo = f["data/demo_1"]
        # default state: every non-image entry in the file's order (h5py lists names alphabetically)
        state = np.concatenate([demo["obs/object"], demo["obs/robot0_eef_pos"]], -1)
        obs = eps["observation", "state"] if image else eps["observation"]
        np.testing.assert_allclose(obs[4:].numpy(), state, rtol=1e-6)
        np.testing.assert_allclose(eps["action"][4:].numpy(), demo["actions"][()], rtol=1e-6)
        if image:
            np.testing.assert_array_equal(
                eps["observation", "rgb"][4:].numpy(), demo["obs/agentview_image"][()].transpose(0, 3, 1, 2)
            )
    assert eps["episode"].tolist() == [0] * 4 + [1] * 6
    assert eps["next", "reward"][:, 0].tolist() == [0, 0, 0, 1, 0, 0, 0, 0, 0, 1]
    assert eps["next", "terminated"][:, 0].nonzero().squeeze(1).tolist() == [3, 9]
    only_object = load_episodes(path, state_keys=["object"], image_key=None)
    assert only_object["observation"].shape == (10, 10)


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_diffusion_policy_zarr(tmp_path, zarr_format):
    path = tmp_path / "pusht_replay.zarr"
    root = write_dp_zarr(path, zarr_format=zarr_format)
    eps = load_episodes(path)
    assert eps["episode"].tolist() == [0, 0, 0, 1, 1, 1, 1, 1]
    assert eps["step"].tolist() == [0, 1, 2, 0, 1, 2, 3, 4]
    np.testing.assert_array_equal(eps["observation", "state"].numpy(), root["data/state"][:])
    np.testing.assert_array_equal(eps["action"].numpy(), root["data/action"][:])
    rgb = eps["observation", "rgb"]
    assert rgb.dtype == torch.uint8 and rgb.shape == (8, 3, 4, 4)
    np.testing.assert_array_equal(rgb.numpy(), root["data/img"][:].transpose(0, 3, 1, 2).astype(np.uint8))
    assert not eps["next", "reward"].any() and eps["next", "done"][:, 0].nonzero().squeeze(1).tolist() == [
        2,
        7,
    ]
    batch = make_chunk_buffer(eps, obs_horizon=2, pred_horizon=4, batch_size=16).sample()
    assert batch["observation", "rgb"].shape == (16, 2, 3, 4, 4)


def test_lerobot_through_torchrl(tmp_path):
    from torchrl.data.datasets.lerobot import lerobot_columns_to_tensordict

    n = 7
    columns = {
        "observation.state": torch.randn(n, 4),
        "observation.images.top": torch.randint(0, 256, (n, 3, 5, 5), dtype=torch.uint8),
        "action": torch.randn(n, 2),
        "episode_index": torch.tensor([0, 0, 0, 1, 1, 1, 1]),
        "frame_index": torch.tensor([0, 1, 2, 0, 1, 2, 3]),
        "next.reward": torch.arange(n, dtype=torch.float32),
        "next.done": torch.tensor([0, 0, 1, 0, 0, 0, 1], dtype=torch.bool),
        "task": ["push"] * n,
    }
    # the layout LeRobotExperienceReplay(repo_id, root=ROOT) keeps on disk after its conversion
    lerobot_columns_to_tensordict(columns).memmap_(tmp_path / "lerobot_pusht")
    eps = load_episodes(tmp_path / "lerobot_pusht")
    assert torch.equal(eps["observation", "state"], columns["observation.state"])
    assert torch.equal(eps["observation", "rgb"], columns["observation.images.top"])
    assert torch.equal(eps["action"], columns["action"])
    assert eps["next", "reward"][:, 0].tolist() == list(range(n))
    assert eps["step"].tolist() == columns["frame_index"].tolist()
    state_only = load_episodes(tmp_path / "lerobot_pusht", camera=None)
    assert state_only["observation"].shape == (n, 4)


def test_raw_lerobot_layout_says_what_is_missing(tmp_path):
    (tmp_path / "raw" / "meta").mkdir(parents=True)
    (tmp_path / "raw" / "meta" / "info.json").write_text("{}")
    with pytest.raises(EpisodeDataError, match=r"codebase_version'.*expects LeRobot v3.0"):
        load_episodes(tmp_path / "raw")


# -- bad input ---------------------------------------------------------------------------------
def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(EpisodeDataError, match=r"nothere\.h5: no such file"):
        load_episodes(tmp_path / "nothere.h5")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(EpisodeDataError, match=r"notes\.txt: not a supported demonstration file"):
        load_episodes(tmp_path / "notes.txt")
    path = tmp_path / "demo.h5"
    write_maniskill(path)
    path.with_suffix(".json").unlink()
    with pytest.raises(
        EpisodeDataError, match=r"demo.h5: a ManiSkill trajectory needs its metadata file .*demo.json"
    ):
        load_episodes(path)


def test_truncated_files(tmp_path):
    path = tmp_path / "demo.h5"
    write_maniskill(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(EpisodeDataError, match=r"demo\.h5: cannot open as HDF5 .*truncated"):
        load_episodes(path)
    # a json that lists an episode the h5 lacks
    path = tmp_path / "short.h5"
    write_maniskill(path, lengths=(3,))
    meta = json.loads(path.with_suffix(".json").read_text())
    meta["episodes"].append({**meta["episodes"][0], "episode_id": 1})
    path.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(
        EpisodeDataError, match=r"short\.h5: episode 1: key 'traj_1': listed in short\.json but missing"
    ):
        load_episodes(path)
    path.with_suffix(".json").write_text('{"env_info": {"env_id"')
    with pytest.raises(EpisodeDataError, match=r"short\.json: not a ManiSkill trajectory metadata file"):
        load_episodes(path)
    zarr_path = tmp_path / "cut.zarr"
    root = write_dp_zarr(zarr_path, img=False)
    root["meta/episode_ends"][:] = np.array([3, 9])
    with pytest.raises(
        EpisodeDataError, match=r"cut\.zarr: episode 1: key 'data/state': has 8 rows but meta/episode_ends"
    ):
        load_episodes(zarr_path)


def test_nan_and_inf_name_file_episode_key(tmp_path):
    path = tmp_path / "demo.h5"
    write_maniskill(path)
    with h5py.File(path, "r+") as f:
        f["traj_1/actions"][3, 2] = np.nan
    with pytest.raises(
        EpisodeDataError,
        match=r"demo.h5: episode 1: key 'traj_1/actions': contains NaN or Inf \(first at step 3\)",
    ):
        load_episodes(path)
    robo = tmp_path / "lift.hdf5"
    write_robomimic(robo, image=False)
    with h5py.File(robo, "r+") as f:
        f["data/demo_0/obs/object"][1, 0] = np.inf
    with pytest.raises(
        EpisodeDataError, match=r"lift\.hdf5: episode demo_0: key 'obs/object': contains NaN or Inf"
    ):
        load_episodes(robo)


def test_mismatched_lengths(tmp_path):
    path = tmp_path / "demo.h5"
    write_maniskill(path, lengths=(5,))
    with h5py.File(path, "r+") as f:
        del f["traj_0/obs"]
        f["traj_0/obs"] = np.zeros((3, 6), np.float32)
    with pytest.raises(
        EpisodeDataError,
        match=r"demo.h5: episode 0: key 'traj_0/obs': has shape \(3, 6\), expected 5 or 6 steps",
    ):
        load_episodes(path)
    robo = tmp_path / "lift.hdf5"
    write_robomimic(robo, image=False)
    with h5py.File(robo, "r+") as f:
        del f["data/demo_1/rewards"]
        f["data/demo_1/rewards"] = np.zeros(2)
    with pytest.raises(
        EpisodeDataError, match=r"lift.hdf5: episode demo_1: key 'rewards': has shape \(2,\), expected 6"
    ):
        load_episodes(robo)


def test_control_mode_mismatch(tmp_path):
    path = tmp_path / "demo.h5"
    write_maniskill(path, control_mode="pd_joint_pos")
    with pytest.raises(
        EpisodeDataError,
        match=r"demo.json: episode 0: key 'control_mode': recorded in 'pd_joint_pos', but 'pd_ee_delta_pos'",
    ):
        load_episodes(path, control_mode="pd_ee_delta_pos")


def test_empty_episode_and_unknown_option(tmp_path):
    path = tmp_path / "empty.zarr"
    write_dp_zarr(path, lengths=(3, 0, 2), img=False)
    with pytest.raises(
        EpisodeDataError, match=r"empty\.zarr: episode 1: key 'meta/episode_ends': the episode has no steps"
    ):
        load_episodes(path)
    write_robomimic(tmp_path / "lift.hdf5")
    with pytest.raises(TypeError, match="option not understood by the robomimic reader"):
        load_episodes(tmp_path / "lift.hdf5", control_mode="pd_ee_delta_pos")


def test_unknown_task_name_is_refused(capsys):
    from l1flow_rl.commands.cli import main

    assert main(["demos", "task=maniskill_nosuchtask", "demos.num=1"]) == 2
    assert "maniskill_nosuchtask" in capsys.readouterr().err


def test_episode_layout_shapes_for_the_loss():
    from l1flow_rl.data.episodes import assemble_episode

    ep = assemble_episode(3, torch.zeros(4, 2), torch.ones(4, 1), reward=torch.arange(4.0), terminated=True)
    assert isinstance(ep, TensorDict) and ep["next", "reward"].shape == (4, 1)
    assert ep["next", "terminated"][:, 0].tolist() == [False, False, False, True]
    assert ep["next", "truncated"].sum() == 0
