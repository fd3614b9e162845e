"""robomimic files in and out, on the real simulator: the exact layout, a round trip, replay from the
first state, observations regenerated from states, states-only imports and malformed files."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest
import torch

pytest.importorskip("robosuite")
pytestmark = pytest.mark.robosuite

from l1flow_rl.envs.robosuite import sim  # noqa: E402
from l1flow_rl.envs.robosuite.dataset import prepare_robomimic_dataset, robosuite_reader_options  # noqa: E402
from l1flow_rl.envs.robosuite.regenerate import regenerate_observations  # noqa: E402

from l1flow_rl.config import load_task_config  # noqa: E402
from l1flow_rl.data import EpisodeDataError, episodes_metadata, load_episodes  # noqa: E402
from l1flow_rl.experts.robosuite.demos import ensure_robosuite_demos  # noqa: E402

#: joint accelerations depend on the last control input, which a MuJoCo state does not hold
NOT_IN_STATE = {"robot0_joint_acc"}


@pytest.fixture(scope="module")
def lift_file(tmp_path_factory):
    task = load_task_config("robosuite_lift")
    path = ensure_robosuite_demos(task, 2, tmp_path_factory.mktemp("rs"), seed=0, workers=1, progress=False)
    return task, path


def test_layout_is_robomimic_exactly(lift_file):
    _, path = lift_file
    with h5py.File(path, "r") as f:
        env_args = json.loads(f["data"].attrs["env_args"])
        assert {"env_name", "env_version", "env_kwargs"} <= set(env_args)
        assert env_args["env_name"] == "Lift" and env_args["type"] == 1
        arm = env_args["env_kwargs"]["controller_configs"]["body_parts"]["right"]
        assert (arm["type"], arm["input_type"], arm["input_ref_frame"]) == ("OSC_POSE", "absolute", "world")
        assert sorted(f["data"]) == ["demo_0", "demo_1"]
        total = 0
        env = sim.make_from_env_args(env_args)
        state_dim = 1 + env.sim.model.nq + env.sim.model.nv
        for name in ("demo_0", "demo_1"):
            demo = f["data"][name]
            steps = demo["actions"].shape[0]
            total += steps
            assert demo.attrs["num_samples"] == steps
            assert demo.attrs["model_file"].startswith("<mujoco")
            assert demo["states"].shape == (steps, state_dim)
            assert demo["actions"].shape == (steps, 7)
            assert demo["rewards"].shape == (steps,) and demo["dones"].shape == (steps,)
            assert demo["dones"][-1] == 1 and demo["dones"][:-1].sum() == 0
            assert demo["rewards"][-1] == 1.0  # sparse: success
            for key in ["object", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"]:
                assert demo["obs"][key].shape[0] == steps and demo["next_obs"][key].shape[0] == steps
            np.testing.assert_array_equal(
                demo["obs"]["robot0_eef_pos"][1:], demo["next_obs"]["robot0_eef_pos"][:-1]
            )
        assert f["data"].attrs["total"] == total
        assert [m.decode() for m in f["mask/train"][()]] == ["demo_0", "demo_1"]
    # two seeds, two different trajectories
    with h5py.File(path, "r") as f:
        a, b = f["data/demo_0/actions"][()], f["data/demo_1/actions"][()]
    assert a.shape != b.shape or np.abs(a - b).max() > 1e-3


def test_round_trip_into_episodes(lift_file):
    task, path = lift_file
    eps = load_episodes(path, **robosuite_reader_options(task))
    with h5py.File(path, "r") as f:
        demo = f["data/demo_0"]
        steps = demo["actions"].shape[0]
        expected = np.concatenate([demo["obs"][k][()] for k in task.state_keys], axis=1)
        final = np.concatenate([demo["next_obs"][k][-1] for k in task.state_keys])
        actions = demo["actions"][()]
    first = eps[eps["episode"] == 0]
    assert first.shape[0] == steps
    torch.testing.assert_close(first["observation"], torch.as_tensor(expected, dtype=torch.float32))
    torch.testing.assert_close(first["action"], torch.as_tensor(actions, dtype=torch.float32))
    torch.testing.assert_close(first["next", "observation"][-1], torch.as_tensor(final, dtype=torch.float32))
    assert bool(first["next", "done"][-1]) and first["next", "reward"][-1].item() == 1.0


def test_replay_from_first_state_reaches_success_and_last_state_is_success(lift_file):
    _, path = lift_file
    with h5py.File(path, "r") as f:
        env_args = json.loads(f["data"].attrs["env_args"])
        demo = f["data/demo_1"]
        states, actions, xml = demo["states"][()], demo["actions"][()], demo.attrs["model_file"]
    env = sim.make_from_env_args(env_args)  # a fresh env
    sim.restore_state(env, states[-1], xml)
    assert env._check_success()
    env = sim.make_from_env_args(env_args)
    sim.restore_state(env, states[0], xml)
    assert not env._check_success()
    for action in actions:
        sim.step(env, action)
    assert env._check_success()


def test_regenerated_observations_match_recorded(lift_file, tmp_path):
    _, path = lift_file
    out = regenerate_observations(
        path, tmp_path / "regen.hdf5", cameras=["agentview"], workers=1, progress=False
    )
    with h5py.File(path, "r") as a, h5py.File(out, "r") as b:
        for name in ("demo_0", "demo_1"):
            recorded, regenerated = a["data"][name]["obs"], b["data"][name]["obs"]
            assert set(regenerated) - set(recorded) == {"agentview_image"}
            for key in set(recorded) - NOT_IN_STATE:
                np.testing.assert_allclose(
                    regenerated[key][()], recorded[key][()], rtol=0, atol=1e-6, err_msg=key
                )
            # next_obs is the next step's obs; only its last row comes from replaying the last action,
            # from a restored state without the controllers' internal state (the gripper's ramped
            # command is not part of a MuJoCo state), so it is close, not equal
            rec_next, reg_next = a["data"][name]["next_obs"], b["data"][name]["next_obs"]
            np.testing.assert_allclose(
                reg_next["robot0_eef_pos"][:-1], rec_next["robot0_eef_pos"][:-1], atol=1e-6
            )
            np.testing.assert_allclose(
                reg_next["robot0_eef_pos"][-1], rec_next["robot0_eef_pos"][-1], atol=0.02
            )
            image = regenerated["agentview_image"]
            assert image.dtype == np.uint8 and image.shape == (len(recorded["object"]), 84, 84, 3)
            for key in ("states", "actions", "rewards", "dones"):
                np.testing.assert_array_equal(b["data"][name][key][()], a["data"][name][key][()])
            assert b["data"][name].attrs["model_file"] == a["data"][name].attrs["model_file"]


def _states_only_copy(src, dst):
    with h5py.File(src, "r") as a, h5py.File(dst, "w") as b:
        b.create_group("data")
        for k, v in a["data"].attrs.items():
            b["data"].attrs[k] = v
        for name in a["data"]:
            g = b["data"].create_group(name)
            for key in ("states", "actions", "rewards", "dones"):
                g.create_dataset(key, data=a["data"][name][key][()])
            for k, v in a["data"][name].attrs.items():
                g.attrs[k] = v


def test_states_only_file_is_refused_by_the_reader_and_imported_by_the_task(lift_file, tmp_path):
    task, path = lift_file
    bare = tmp_path / "states_only.hdf5"
    _states_only_copy(path, bare)
    with pytest.raises(EpisodeDataError, match=r"demo_0: key 'obs': missing.*regenerate"):
        load_episodes(bare, **robosuite_reader_options(task))
    imported = prepare_robomimic_dataset(task, bare, tmp_path / "data", workers=1)
    assert imported != bare and imported.parent == tmp_path / "data" / "robosuite" / "imported"
    assert prepare_robomimic_dataset(task, bare, tmp_path / "data", workers=1) == imported  # cached
    assert prepare_robomimic_dataset(task, path, tmp_path / "data") == path  # has its observations
    a = load_episodes(path, **robosuite_reader_options(task))
    b = load_episodes(imported, **robosuite_reader_options(task))
    torch.testing.assert_close(b["observation"], a["observation"], rtol=0, atol=1e-6)


@pytest.fixture
def broken(lift_file, tmp_path):
    _, path = lift_file

    def make(edit):
        copy = tmp_path / "broken.hdf5"
        shutil.copy(path, copy)
        with h5py.File(copy, "r+") as f:
            edit(f)
        return copy

    return make


def test_missing_states_names_demo_and_key(broken, tmp_path):
    def drop(f):
        del f["data/demo_1/states"]

    with pytest.raises(EpisodeDataError, match=r"demo_1: key 'states': missing"):
        regenerate_observations(broken(drop), tmp_path / "out.hdf5", workers=1, progress=False)
    assert not (tmp_path / "out.hdf5").exists()


def test_wrong_action_width_names_demo_and_key(broken, lift_file):
    task, _ = lift_file

    def widen(f):
        actions = f["data/demo_1/actions"][()]
        del f["data/demo_1/actions"]
        f["data/demo_1"].create_dataset("actions", data=np.concatenate([actions, actions[:, :1]], 1))

    with pytest.raises(
        EpisodeDataError, match=r"demo_1: key 'actions': 8 action dims, but the recorded controller"
    ):
        load_episodes(broken(widen), **robosuite_reader_options(task))


def test_nan_names_demo_key_and_step(broken, lift_file):
    task, _ = lift_file

    def poison(f):
        f["data/demo_0/actions"][3, 2] = np.nan

    with pytest.raises(
        EpisodeDataError, match=r"demo_0: key 'actions': contains NaN or Inf \(first at step 3\)"
    ):
        load_episodes(broken(poison), **robosuite_reader_options(task))


def test_truncated_file_names_the_file(lift_file, tmp_path):
    task, path = lift_file
    cut = tmp_path / "cut.hdf5"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(EpisodeDataError, match=r"cut\.hdf5"):
        load_episodes(cut, **robosuite_reader_options(task))


def test_robosuite_1_4_controller_config_is_translated(lift_file, broken):
    """A file from robomimic's era (robosuite <= 1.4: one part config with control_delta) replays."""
    task, _ = lift_file

    def old_style(f):
        env_args = json.loads(f["data"].attrs["env_args"])
        arm = env_args["env_kwargs"]["controller_configs"]["body_parts"]["right"]
        old = {k: v for k, v in arm.items() if k not in ("input_type", "input_ref_frame", "gripper")}
        old["control_delta"] = False
        env_args["env_kwargs"]["controller_configs"] = old
        env_args["env_version"] = "1.4.1"
        f["data"].attrs["env_args"] = json.dumps(env_args)

    path = broken(old_style)
    eps = load_episodes(path, **robosuite_reader_options(task))
    meta = episodes_metadata(eps)
    assert (meta.control, meta.control_mode) == ("absolute", "OSC_POSE")
    with h5py.File(path, "r") as f:
        env_args = json.loads(f["data"].attrs["env_args"])
        demo = f["data/demo_0"]
        states, actions, xml = demo["states"][()], demo["actions"][()], demo.attrs["model_file"]
    env = sim.make_from_env_args(env_args)
    arm = env.robots[0].composite_controller.part_controllers["right"]
    assert (arm.input_type, arm.input_ref_frame) == ("absolute", "world")
    sim.restore_state(env, states[0], xml)
    for action in actions:
        sim.step(env, action)
    assert env._check_success()
