"""Object-centric shifts of absolute-control episodes (demos.shifted_replays): the weights, the
shifted and turned actions, their errors, the nearest-source choice, and real robosuite Can and
Square files grown by shifted replays."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from l1flow_rl.config import load_task_config
from l1flow_rl.experts.object_shift import final_grasp, shift_actions, shift_weights
from l1flow_rl.experts.quality import GripperLayout

GRIP = GripperLayout("absolute", open=-1.0, closed=1.0)


def _episode(gripper: list[float]) -> np.ndarray:
    actions = np.zeros((len(gripper), 7))
    actions[:, :3] = np.arange(len(gripper))[:, None] * 0.01
    actions[:, -1] = gripper
    return actions


def test_the_final_grasp_is_the_last_closed_run_and_its_release():
    # open 0-3, a false grasp 4-5, open 6-7, the grasp 8-13, released at 14
    actions = _episode([-1] * 4 + [1] * 2 + [-1] * 2 + [1] * 6 + [-1] * 3)
    assert final_grasp(actions, GRIP) == (8, 14)
    assert final_grasp(_episode([-1, -1, 1, 1]), GRIP) == (2, 4)  # never released: the end
    with pytest.raises(ValueError, match="never closes the gripper"):
        final_grasp(_episode([-1] * 5), GRIP)


def test_the_weights_follow_the_object_until_the_lift_then_fade_to_the_release():
    actions = _episode([-1] * 4 + [1] * 10 + [-1] * 3)  # grasp 4-13, released at 14
    w = shift_weights(actions, GRIP, hold=2)
    assert np.all(w[:6] == 1.0)  # the approach, the close and `hold` steps of the lift
    assert np.all(np.diff(w[6:14]) < 0) and w[13] > 0  # fading during the carry
    assert np.all(w[14:] == 0.0)  # the release and after: the recorded place
    assert w.shape == (17,)
    with pytest.raises(ValueError, match="hold=-1"):
        shift_weights(actions, GRIP, hold=-1)


def test_shifted_actions_move_only_the_position_targets_by_the_weighted_offset():
    actions = _episode([-1] * 4 + [1] * 10 + [-1] * 3)
    actions[:, 3:6] = [0.1, -0.2, 0.3]
    out = shift_actions(actions, np.array([0.05, -0.02]), GRIP, hold=2)
    w = shift_weights(actions, GRIP, hold=2)
    np.testing.assert_allclose(out[:, 0] - actions[:, 0], 0.05 * w)
    np.testing.assert_allclose(out[:, 1] - actions[:, 1], -0.02 * w)
    np.testing.assert_array_equal(out[:, 2:], actions[:, 2:])  # z, rotation and gripper untouched
    assert out is not actions and np.all(actions[:, 0] == np.arange(17) * 0.01)
    with pytest.raises(ValueError, match="shape \\(4,\\)"):
        shift_actions(actions, np.zeros(4), GRIP)
    with pytest.raises(ValueError, match="control is 'delta'"):
        shift_actions(actions, np.zeros(2), GripperLayout("delta", open=-1.0, closed=1.0))


def test_a_turned_shift_turns_the_targets_about_the_object_with_the_weights():
    actions = _episode([-1] * 4 + [1] * 10 + [-1] * 3)  # grasp 4-13, released at 14
    top_down = Rotation.from_euler("xyz", [np.pi, 0.0, 0.3])
    actions[:, 3:6] = top_down.as_rotvec()
    pivot, offset, turn = np.array([0.02, -0.01]), np.array([0.03, 0.04]), 0.4
    out = shift_actions(actions, offset, GRIP, hold=2, turn=turn, pivot=pivot)
    w = shift_weights(actions, GRIP, hold=2)
    for t in range(len(actions)):
        c, s = np.cos(w[t] * turn), np.sin(w[t] * turn)
        rel = actions[t, :2] - pivot
        expected = pivot + np.array([c * rel[0] - s * rel[1], s * rel[0] + c * rel[1]]) + w[t] * offset
        np.testing.assert_allclose(out[t, :2], expected, atol=1e-12)
        # the orientation turns by w * turn about the vertical: same roll/pitch, yaw + w * turn
        turned = Rotation.from_rotvec(out[t, 3:6])
        assert (turned * top_down.inv()).magnitude() == pytest.approx(w[t] * turn, abs=1e-9)
        np.testing.assert_allclose((turned * top_down.inv()).as_rotvec()[:2], 0.0, atol=1e-9)
    np.testing.assert_array_equal(out[:, 2], actions[:, 2])  # height and gripper untouched
    np.testing.assert_array_equal(out[:, 6], actions[:, 6])
    np.testing.assert_allclose(out[14:], actions[14:], atol=1e-12)  # the place: as recorded
    # a top-down gripper sits at ~pi, where axis-angle has two sides: the source's side is kept
    assert np.abs(np.diff(out[:, 3:6], axis=0)).max() < 0.1
    with pytest.raises(ValueError, match="pivot"):
        shift_actions(actions, offset, GRIP, turn=0.4)
    with pytest.raises(ValueError, match="OSC_POSE"):
        shift_actions(actions[:, [0, 1, 2, 6]], offset, GRIP, turn=0.4, pivot=pivot)


def test_a_turning_object_replays_one_of_its_nearest_sources():
    from l1flow_rl.experts.robosuite.shifted import NEAREST_K, Source, nearest_sources

    def source(name, x, yaw):
        return Source(name, np.zeros(1), np.zeros((2, 7)), np.array([x, 0.0, 0.8]), yaw)

    sources = [source("a", 0.0, 3.1), source("b", 0.0, 0.0), source("c", 0.05, 0.1), source("d", 0.0, -3.1)]
    # metres plus radians, the yaw wrapped: -3.1 and 3.1 are 0.08 apart, not 6.2
    near = nearest_sources(sources, np.array([0.0, 0.0, 0.8]), -3.12)
    assert NEAREST_K == 3 and [s.name for s in near] == ["d", "a", "c"]


@pytest.mark.robosuite
def test_shifted_replays_grow_a_can_file_with_successes_labelled_shifted(tmp_path):
    pytest.importorskip("robosuite")
    from l1flow_rl.data import load_episodes
    from l1flow_rl.experts import ensure_demos
    from l1flow_rl.experts.robosuite.shifted import SHIFT_SEEDS

    task = load_task_config("robosuite_can")
    path = ensure_demos(task, 2, tmp_path, shifted_replays=4, workers=1, progress=False)
    assert path.name.endswith(".n2.shift4.hdf5")
    with h5py.File(path, "r") as f:
        import json

        stats = json.loads(f["data"].attrs["shifted_replays"])
        names = sorted(f["data"], key=lambda n: int(n.split("_")[1]))
        shifted = sorted(m.decode() for m in f["mask"]["shifted"][()])
        assert stats["attempts"] == 4 and stats["source_episodes"] == 2 and stats["seeds_from"] == SHIFT_SEEDS
        assert len(names) == 2 + stats["successes"] and shifted == names[2:]
        assert sorted(m.decode() for m in f["mask"]["train"][()]) == sorted(names)
        # each attempt is one episode of env steps, failures included
        assert stats["env_steps"] >= sum(f["data"][n].attrs["num_samples"] for n in shifted)
        assert stats["successes"] >= 3  # measured: 194 of 200 on the mixed-30 set
        for n in shifted:
            g = f["data"][n]
            assert g.attrs["quality"] == "shifted" and g.attrs["success"]
            assert g.attrs["source_demo"] in names[:2] and g["rewards"][()].max() > 0
            assert np.linalg.norm(g.attrs["offset_xy"]) > 0
            assert g.attrs["seed"] >= SHIFT_SEEDS
        # the scene is another one: the first stored states differ from the source's
        source = f["data"][shifted[0]].attrs["source_demo"]
        assert not np.allclose(f["data"][shifted[0]]["states"][0], f["data"][source]["states"][0])
    eps = load_episodes(path, labels=["shifted"], state_keys=list(task.state_keys), image_key=None)
    assert int(eps["episode"].unique().numel()) == stats["successes"]
    # the base file is made once and kept beside the grown one
    base = path.parent / path.name.replace(".shift4", "")
    assert base.is_file()
    _base_episodes_and_attributes_go_on_verbatim(task, base, tmp_path)


def _base_episodes_and_attributes_go_on_verbatim(task, base, tmp_path):
    """A base file with what our writer never writes (a data attribute, an episode dataset, a gap in
    the demo names that its masks refer to): the grown file keeps all of it, and the replays are
    named past the last base episode."""
    import shutil

    from l1flow_rl.experts.robosuite.shifted import add_shifted_replays

    user = tmp_path / "user.hdf5"
    shutil.copy(base, user)
    with h5py.File(user, "a") as f:
        f["data"].attrs["date"] = "2026-11-29"
        f["data"].move("demo_1", "demo_7")
        f["data"]["demo_7"].create_dataset(
            "action_dict/grip", data=np.arange(len(f["data"]["demo_7"]["actions"]))
        )
        masks = f.require_group("mask")
        if "train" in masks:
            del masks["train"]
        masks.create_dataset("train", data=np.array(["demo_0", "demo_7"], dtype="S"))
    grown = add_shifted_replays(task, user, tmp_path / "grown.hdf5", 2, workers=1, progress=False)
    with h5py.File(user, "r") as u, h5py.File(grown, "r") as g:
        added = [m.decode() for m in g["mask"]["shifted"][()]]
        assert g["data"].attrs["date"] == "2026-11-29"
        assert added and all(int(n.split("_")[1]) > 7 for n in added)
        assert [m.decode() for m in g["mask"]["train"][()]] == ["demo_0", "demo_7", *added]
        for name in ("demo_0", "demo_7"):
            for key in ("states", "actions", "rewards", "dones"):
                np.testing.assert_array_equal(g["data"][name][key][()], u["data"][name][key][()])
            assert dict(g["data"][name].attrs).keys() == dict(u["data"][name].attrs).keys()
        np.testing.assert_array_equal(
            g["data"]["demo_7"]["action_dict/grip"][()], u["data"]["demo_7"]["action_dict/grip"][()]
        )
        assert g["data"].attrs["total"] == sum(len(g["data"][n]["actions"]) for n in g["data"])


@pytest.mark.robosuite
def test_a_square_file_grows_by_turned_replays_and_a_lift_file_is_refused_first(tmp_path):
    pytest.importorskip("robosuite")
    import json

    from l1flow_rl.experts import ensure_demos
    from l1flow_rl.experts.registry import DemoGenerationError

    task = load_task_config("robosuite_square")
    path = ensure_demos(task, 8, tmp_path, shifted_replays=4, workers=1, progress=False)
    with h5py.File(path, "r") as f:
        stats = json.loads(f["data"].attrs["shifted_replays"])
        shifted = [f["data"][m.decode()] for m in f["mask"]["shifted"][()]]
        assert stats["attempts"] == 4 and stats["source_episodes"] == 8
        # measured: 3 of the first 8 attempts from 8 sources (turns up to ~0.5 rad), 1 of 8 from 3,
        # 14 of 16 from 50 (the nearest source's turn shrinks as the sources cover the yaws)
        assert stats["successes"] >= 1 and len(shifted) == stats["successes"]
        assert len(stats["failed"]) == 4 - stats["successes"]  # each failure named, not only counted
        assert all(set(f) == {"seed", "source_demo", "offset_xy", "turn"} for f in stats["failed"])
        for g in shifted:
            assert g.attrs["success"] and g.attrs["quality"] == "shifted"
            assert abs(g.attrs["turn"]) <= np.pi and g.attrs["source_demo"] in {f"demo_{i}" for i in range(8)}
    # refused before any demonstration is made (robosuite Lift: nothing to shift it to)
    with pytest.raises(
        DemoGenerationError, match=r"shifted_replays=3: task 'robosuite_lift'.*NutAssemblySquare"
    ):
        ensure_demos(
            load_task_config("robosuite_lift"), 2, tmp_path / "lift", shifted_replays=3, progress=False
        )
    assert not (tmp_path / "lift").exists() or not any((tmp_path / "lift").rglob("*.hdf5"))


def test_shifted_replays_refuse_an_expert_without_them():
    from omegaconf import OmegaConf

    from l1flow_rl.experts.options import demo_options
    from l1flow_rl.experts.registry import DemoGenerationError

    cfg = OmegaConf.create({"demos": {"num": 3, "seed": 0, "quality": "expert", "shifted_replays": 5}})
    with pytest.raises(DemoGenerationError, match=r"demos\.shifted_replays=5: the pusht expert"):
        demo_options(cfg, load_task_config("pusht_state"))


def test_shifted_replays_are_refused_beside_a_users_file_and_below_zero():
    from l1flow_rl.commands.cli import compose_config
    from l1flow_rl.config.validate import ConfigValidationError

    with pytest.raises(ConfigValidationError, match=r"demos\.shifted_replays=5: it grows the expert's"):
        compose_config(["task=robosuite_can", "demos.shifted_replays=5", "data.path=mine.hdf5"])
    with pytest.raises(ConfigValidationError, match=r"demos\.shifted_replays=-1: expected"):
        compose_config(["task=robosuite_can", "demos.shifted_replays=-1"])
    # a fine-tune adopts its start's data.path after composing: the dataset step refuses it then
    from omegaconf import open_dict

    from l1flow_rl.workspace.dataset import resolve_dataset

    cfg = compose_config(["task=robosuite_can", "demos.shifted_replays=5"])
    with open_dict(cfg):
        cfg.data.path = "mine.hdf5"
    with pytest.raises(ConfigValidationError, match=r"not data\.path='mine\.hdf5'"):
        resolve_dataset(cfg)
