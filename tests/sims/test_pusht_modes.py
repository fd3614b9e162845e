"""PushT's route rule and the modes benchmark on the real simulator: hand-made paths get the route
they were drawn with, the rule agrees with the planner's own side where the planner chose freely,
keypoint observations decode to gym-pusht's state, and ``benchmarks.success.bench_pusht_modes --quick``
runs end to end on a tiny trained checkpoint."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from l1flow_rl.envs.pusht.geometry import BLOCK_COG, DP_BLOCK_KEYPOINTS, block_keypoints, to_world

from l1flow_rl.experts.pusht.routes import agent_gap, classify_approach, pose_from_points, sim_states

pytest.importorskip("gym_pusht", reason="needs gym-pusht: pip install 'l1flow-rl[pusht]'")
pytestmark = pytest.mark.pusht

#: Diffusion Policy test seeds where the planner's first way to the block is a free choice, one
#: each way (found by running the planner on seeds 100000-100049: 100003 goes right, 100004 left)
BIMODAL = {100003: "right", 100004: "left"}

POSE = np.array([256.0, 256.0, 0.0])  # the T upright: bar on top (y 256..286), stem below it


def _arc(start_deg: float, end_deg: float, radius: float = 110.0, steps: int = 30) -> np.ndarray:
    """Agent positions on a circle around the T's centre, then a straight leg onto the T's bar."""
    centre = to_world(BLOCK_COG[None], POSE)[0]
    angles = np.radians(np.linspace(start_deg, end_deg, steps))
    arc = centre + radius * np.stack([np.cos(angles), np.sin(angles)], -1)
    into = np.linspace(arc[-1], centre, 12)[1:]
    return np.concatenate([arc, into])


def _classify(agent: np.ndarray):
    return classify_approach(agent, np.repeat(POSE[None], len(agent), 0))


def test_gap_is_zero_on_the_block_and_grows_off_it():
    agent = np.array([[256.0, 250.0], [256.0, 200.0], [256.0, 300.0], [300.0, 340.0]])
    # above the bar's top edge (y = 256) by 6 px minus the radius; 56 - 15; inside the stem; beside it
    np.testing.assert_allclose(agent_gap(agent, np.repeat(POSE[None], 4, 0)), [0.0, 41.0, 0.0, 14.0])


def test_counter_clockwise_sweep_is_left_clockwise_is_right():
    # start below the stem's foot (90 deg in atan2 terms, y down) and go round to the bar's top (-90)
    left = _classify(_arc(90, 270))  # increasing atan2 angle: counter-clockwise
    right = _classify(_arc(90, -90))
    assert left.route == "left" and math.degrees(left.sweep) == pytest.approx(180, abs=2)
    assert right.route == "right" and math.degrees(right.sweep) == pytest.approx(-180, abs=2)
    assert left.start_step == 0 and left.contact_step is not None and left.contact_step > 29


def test_straight_in_is_between_and_never_touching_is_no_contact():
    centre = to_world(BLOCK_COG[None], POSE)[0]
    straight = np.linspace([256.0, 60.0], centre, 20)  # from above the bar, down onto it
    between = _classify(straight)
    assert between.route == "between" and abs(between.sweep) < 1e-9
    assert between.contact_step is not None
    # the arc alone (the final leg onto the block cut off) never touches
    away = classify_approach(_arc(90, 200, radius=200, steps=10)[:10], np.repeat(POSE[None], 10, 0))
    assert away.route == "no_contact" and away.contact_step is None
    assert math.degrees(away.sweep) == pytest.approx(110, abs=1)


def test_an_agent_that_starts_on_the_block_is_measured_from_where_it_leaves():
    centre = to_world(BLOCK_COG[None], POSE)[0]
    on_block = np.repeat(centre[None], 3, 0)
    left = _classify(np.concatenate([on_block, _arc(90, 270)]))
    assert left.route == "left" and left.start_step == 3
    stays = _classify(on_block)
    assert stays.route == "between" and stays.start_step is None and stays.contact_step is None


def test_bad_shapes_and_threshold_are_refused():
    with pytest.raises(ValueError, match=r"\[T, 2\].*\[T, 3\]"):
        classify_approach(np.zeros((5, 2)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="threshold"):
        classify_approach(np.zeros((5, 2)), np.zeros((5, 3)), threshold=0.0)
    with pytest.raises(ValueError, match="obs_mode"):
        sim_states(np.zeros((3, 2)), "pixels_agent_pos")


def test_keypoint_observations_decode_to_gym_pushts_state():
    from l1flow_rl.envs.pusht import PushTEnv

    from l1flow_rl.config import load_task_config

    env = PushTEnv(load_task_config("pusht"), render=False)
    try:
        for seed in (100003, 100004, 7):
            obs = env.reset(seed=seed)["observation"].numpy()
            state = env.sim_state()
            np.testing.assert_allclose(sim_states(obs, "keypoints"), state, atol=2e-3)
    finally:
        env.close()
    pose = np.array([[100.0, 200.0, 5.5], [300.0, 50.0, 0.25]])
    states = np.concatenate([np.zeros((2, 2)), pose], -1)
    np.testing.assert_allclose(pose_from_points(block_keypoints(states), DP_BLOCK_KEYPOINTS), pose, atol=1e-9)


@pytest.fixture(scope="module")
def expert_demos():
    from l1flow_rl.experts.pusht.episode import run_episode

    return {seed: run_episode(seed, max_steps=60) for seed in BIMODAL}


def test_rule_agrees_with_the_planners_free_choice(expert_demos):
    for seed, side in BIMODAL.items():
        demo = expert_demos[seed]
        assert demo is not None
        assert (demo.first_side, demo.first_chosen) == (side, True)
        states = demo.arrays["state"].astype(np.float64)
        approach = classify_approach(states[:, :2], states[:, 2:5])
        assert approach.route == side, (seed, math.degrees(approach.sweep))
        assert approach.contact_step is not None


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    from l1flow_rl.commands.cli import main

    root = tmp_path_factory.mktemp("pusht_modes")
    run_dir = root / "run"
    args = [
        "train",
        "task=pusht",
        "demos.num=3",
        "train.steps=20",
        "eval.enabled=false",  # no evaluation: the benchmark rolls the checkpoint out itself
        "train.batch_size=16",
        "network.down_dims=[16,32]",
        "network.timestep_embed_dim=16",
        f"data_dir={root / 'data'}",
        f"run_dir={run_dir}",
    ]
    assert main(args) == 0
    return run_dir


def test_quick_benchmark_reports_routes_per_policy(tiny_checkpoint, tmp_path):
    from benchmarks.success import bench_pusht_modes

    out = tmp_path / "pusht_modes.json"
    argv = ["--quick", "--quiet", "--first-seed", "100003", "--runs", str(tiny_checkpoint), "--out", str(out)]
    argv += ["--checkpoints", f"again={tiny_checkpoint / 'checkpoints' / 'latest.pt'}"]
    assert bench_pusht_modes.main(argv) == 0
    figures = json.loads(out.read_text())
    assert figures["quick"] is True and figures["protocol"]["max_episode_steps"] == 60
    assert figures["bimodal_seeds"] == [100003, 100004]
    expert = figures["policies"]["expert"]
    assert expert["agreement_on_bimodal"] == 1.0
    assert expert["routes_bimodal"]["counts"] == {"left": 1, "right": 1, "between": 0, "no_contact": 0}
    assert set(figures["policies"]) == {"expert", "l1flow", "again"}
    for name in ("l1flow", "again"):
        block = figures["policies"][name]
        assert block["episodes"] == 2 and [e["seed"] for e in block["per_episode"]] == [100003, 100004]
        assert block["routes_all"]["n"] == 2 and sum(block["routes_all"]["counts"].values()) == 2
        assert 0.0 <= block["score"] <= 1.0 and block["ci95"]["success"][0] <= block["success"]
    # the same checkpoint, the same seeds and the same policy noise: the same episodes
    assert figures["policies"]["l1flow"]["per_episode"] == figures["policies"]["again"]["per_episode"]
    assert (tmp_path / "pusht_modes.png").stat().st_size > 0


def test_benchmark_refuses_unnamed_or_missing_checkpoints(tmp_path):
    from benchmarks.success import bench_pusht_modes

    with pytest.raises(SystemExit):
        bench_pusht_modes.main(["--quick", "--checkpoints", "no_equals_sign"])
    with pytest.raises(ValueError, match="NAME=PATH"):
        bench_pusht_modes.parse_policies(["no_equals_sign"], [])
    with pytest.raises(FileNotFoundError, match="neither"):
        bench_pusht_modes.run_checkpoint(tmp_path)
    with pytest.raises(FileNotFoundError, match="not found"):
        bench_pusht_modes.parse_policies([f"x={tmp_path / 'nope.pt'}"], [])
