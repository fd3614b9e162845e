"""Mixed-quality demonstrations (demos.quality=mixed): the perturbations, the labels a file carries
through a write and a read, filtering by label, and the config checks; on the real simulators."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from omegaconf import OmegaConf

from l1flow_rl.config import AppConfig, load_task_config
from l1flow_rl.config.validate import ConfigValidationError, validate_config
from l1flow_rl.data import EpisodeDataError, load_episodes
from l1flow_rl.experts.quality import GripperLayout, label_of, mixed_kinds, perturb_actions

ABSOLUTE = GripperLayout("absolute", open=-1.0, closed=1.0)
DELTA = GripperLayout("delta", open=1.0, closed=-1.0, metres_per_unit=0.1)


def _episode(grip: GripperLayout, steps: int = 60, close_at: int = 30) -> np.ndarray:
    actions = np.zeros((steps, 7 if grip.control == "absolute" else 4))
    if grip.control == "absolute":
        actions[:, :3] = np.linspace([0.0, 0.0, 1.0], [0.1, 0.0, 0.9], steps)
    else:
        actions[:, 2] = -0.05
    actions[:, -1] = grip.open
    actions[close_at:, -1] = grip.closed
    return actions


def test_mixed_kinds_follow_the_shares_and_the_seed():
    kinds = mixed_kinds(100, seed=3)
    assert {k: kinds.count(k) for k in set(kinds)} == {"expert": 40, "noisy": 25, "recovered": 20, "drop": 15}
    assert kinds == mixed_kinds(100, seed=3) and kinds != mixed_kinds(100, seed=4)
    # shares round per kind (3 episodes: 1 noisy, 1 recovered, 0 drop); the expert takes the rest
    assert sorted(mixed_kinds(3, seed=0)) == ["expert", "noisy", "recovered"]
    assert label_of("noisy", False) == "failed" and label_of("drop", True) == "recovered"


@pytest.mark.parametrize("grip", [ABSOLUTE, DELTA], ids=["absolute", "delta"])
def test_a_false_grasp_closes_above_the_object_reopens_and_returns(grip):
    actions = _episode(grip)
    out = perturb_actions(actions, "recovered", np.random.default_rng(0), grip)
    inserted = len(out) - len(actions)
    assert inserted > 0
    np.testing.assert_array_equal(out[:30], actions[:30])
    np.testing.assert_array_equal(out[30 + inserted :], actions[30:])  # then the expert's grasp
    middle = out[30 : 30 + inserted]
    closed = [grip.is_closed(g) for g in middle[:, -1]]
    assert any(closed) and not closed[0] and not closed[-1]  # closes on nothing, opens again
    rise = middle[:, 2] - actions[29, 2] if grip.control == "absolute" else np.cumsum(middle[:, 2]) * 0.1
    at_close = rise[closed.index(True)]
    assert 0.03 <= at_close <= 0.06 + 1e-9  # 3-6 cm above the grasp
    assert abs(rise[-1]) < 1e-9  # back where the expert closes


@pytest.mark.parametrize("grip", [ABSOLUTE, DELTA], ids=["absolute", "delta"])
def test_noise_adds_pauses_and_a_drop_opens_during_the_carry(grip):
    actions = _episode(grip)
    noisy = perturb_actions(actions, "noisy", np.random.default_rng(1), grip)
    assert len(actions) + 4 <= len(noisy) <= len(actions) + 36  # 1-3 pauses of 4-12 steps
    assert not np.allclose(noisy[: len(actions), :3], actions[:, :3])
    np.testing.assert_array_equal(np.unique(noisy[:, -1]), np.unique(actions[:, -1]))  # gripper untouched
    dropped = perturb_actions(actions, "drop", np.random.default_rng(2), grip)
    opened = np.flatnonzero(dropped[30:, -1] == grip.open)
    assert 12 <= opened[0] < 25 and (dropped[30 + opened[0] :, -1] == grip.open).all()
    np.testing.assert_array_equal(dropped[:, :-1], actions[:, :-1])
    with pytest.raises(ValueError, match=r"unknown perturbation 'wobble'"):
        perturb_actions(actions, "wobble", np.random.default_rng(0), grip)


def test_config_names_unknown_labels_and_qualities():
    cfg = OmegaConf.structured(AppConfig)
    cfg.data.labels, cfg.demos.quality = ["expert", "great"], "mixd"
    with pytest.raises(ConfigValidationError) as err:
        validate_config(cfg, "train")
    assert "data.labels=['expert', 'great']: unknown label(s) ['great']" in str(err.value)
    assert "demos.quality='mixd': expected one of ['expert', 'mixed']" in str(err.value)


def test_a_task_whose_expert_makes_no_mixed_set_is_refused():
    from l1flow_rl.commands.demos import demo_options
    from l1flow_rl.experts import DemoGenerationError

    cfg = OmegaConf.structured(AppConfig)
    cfg.demos.quality = "mixed"
    with pytest.raises(DemoGenerationError, match=r"demos.quality='mixed': the pusht expert makes expert"):
        demo_options(cfg, load_task_config("pusht"))


def _check_round_trip(path, labels: list[str], **options) -> None:
    """Every label the file records comes back from the reader; filtering keeps exactly those."""
    assert sorted(set(labels)) == sorted(set(labels) & {"expert", "noisy", "recovered", "failed"})
    assert "expert" in labels and len(set(labels)) >= 3
    for wanted in (["expert"], [lb for lb in set(labels) if lb != "expert"]):
        eps = load_episodes(path, labels=wanted, **options)
        expected = [i for i, lb in enumerate(labels) if lb in wanted]
        assert eps["episode"].unique().tolist() == expected
        ended = eps["next", "done"].squeeze(-1) | eps["next", "truncated"].squeeze(-1)
        for episode in expected:
            rows = eps["episode"] == episode
            reward = eps["next", "reward"][rows].sum().item()
            if labels[episode] == "failed":
                assert not eps["next", "terminated"][rows].any()  # cut short, never terminated
            else:
                assert eps["next", "terminated"][rows][-1] and reward > 0
            assert ended[rows][-1]
    absent = [lb for lb in ("noisy", "recovered", "failed") if lb not in labels]
    for label in absent:
        with pytest.raises(EpisodeDataError, match=rf"no episode is labelled \['{label}'\]"):
            load_episodes(path, labels=[label], **options)


@pytest.mark.robosuite
def test_a_mixed_square_file_round_trips_its_labels_and_filters_by_them(tmp_path):
    pytest.importorskip("robosuite")
    from l1flow_rl.experts import ensure_demos

    task = load_task_config("robosuite_square")
    path = ensure_demos(task, 6, tmp_path, quality="mixed", workers=2, progress=False)
    assert path.name.endswith(".n6.mixed.hdf5")
    with h5py.File(path, "r") as f:
        names = [f"demo_{i}" for i in range(6)]
        labels = [f["data"][n].attrs["quality"] for n in names]
        kinds = [f["data"][n].attrs.get("perturbation", "expert") for n in names]
        for label in ("expert", "noisy", "recovered", "failed"):  # robomimic's filter keys agree
            assert sorted(m.decode() for m in f["mask"][label][()]) == [
                n for n, lb in zip(names, labels) if lb == label
            ]
        assert len(f["mask"]["train"]) == 6
    assert kinds == mixed_kinds(6, 0)
    assert all(lb in ("failed", k) or (k, lb) == ("drop", "recovered") for k, lb in zip(kinds, labels))
    options = {"state_keys": list(task.state_keys), "image_key": None}
    _check_round_trip(path, labels, **options)


@pytest.mark.maniskill
@pytest.mark.slow  # ~70 s: 10 PickCube plans and replays, then the perturbed episodes
def test_a_mixed_pickcube_file_round_trips_its_labels_and_filters_by_them(tmp_path):
    pytest.importorskip("mani_skill")
    import json

    from l1flow_rl.experts import ensure_demos

    task = load_task_config("maniskill_pickcube")
    path = ensure_demos(task, 10, tmp_path, quality="mixed", workers=1, progress=False)
    assert path.name.endswith(".n10.mixed.h5")
    episodes = json.loads(path.with_suffix(".json").read_text())["episodes"]
    assert [e["perturbation"] for e in episodes] == mixed_kinds(10, 0)
    labels = [e["quality"] for e in episodes]
    assert all(e["success"] == (e["quality"] != "failed") for e in episodes)
    _check_round_trip(path, labels, control_mode=task.control_mode)
