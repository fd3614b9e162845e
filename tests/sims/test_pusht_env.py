"""The PushT adapter on the real gym-pusht simulator: specs, observations, Diffusion Policy's score."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from l1flow_rl.envs.pusht.env import PushTEnv
from l1flow_rl.envs.pusht.geometry import (
    DP_BLOCK_KEYPOINTS,
    block_keypoints,
    compute_dp_block_keypoints,
    reset_state_for,
)
from torchrl.envs.utils import check_env_specs

from l1flow_rl.config import load_task_config

pytest.importorskip("gym_pusht", reason="needs gym-pusht: pip install 'l1flow-rl[pusht]'")
pytestmark = pytest.mark.pusht


@pytest.mark.parametrize(
    ("obs_mode", "shape"),
    [
        ("state", (5,)),
        ("keypoints", (20,)),
        ("environment_state_agent_pos", (18,)),
        ("pixels", None),
        ("pixels_agent_pos", None),
    ],
)
def test_check_env_specs_per_obs_mode(obs_mode, shape):
    env = PushTEnv(load_task_config("pusht", obs_mode=obs_mode, max_episode_steps=20))
    check_env_specs(env, seed=0)
    obs = env.reset(seed=3)["observation"]
    if shape is not None:
        assert obs.shape == shape and obs.dtype == torch.float32
    else:
        assert obs["rgb"].shape == (3, 96, 96) and obs["rgb"].dtype == torch.uint8
        assert obs["rgb"].float().std() > 10  # a real picture, not a blank
        assert ("state" in obs) == (obs_mode == "pixels_agent_pos")
    rollout = env.rollout(5)
    assert rollout["next", "coverage"].shape == (5, 1)
    assert ((rollout["next", "coverage"] >= 0) & (rollout["next", "coverage"] <= 1)).all()
    env.close()


def test_keypoint_observation_matches_diffusion_policy_layout():
    env = PushTEnv(load_task_config("pusht"))
    state_env = PushTEnv(load_task_config("pusht_state"))
    kp = env.reset(seed=11)["observation"].numpy()
    state = state_env.reset(seed=11)["observation"].numpy()
    np.testing.assert_allclose(kp[:18].reshape(9, 2), block_keypoints(state), atol=1e-3)
    np.testing.assert_allclose(kp[18:], state[:2])
    # a keypoint moves rigidly with the block: distances between keypoints never change
    d0 = np.linalg.norm(DP_BLOCK_KEYPOINTS[0] - DP_BLOCK_KEYPOINTS[1])
    assert np.linalg.norm(kp[0:2] - kp[2:4]) == pytest.approx(d0, abs=1e-3)


def test_dp_keypoints_recomputed_from_the_recipe():
    np.testing.assert_allclose(compute_dp_block_keypoints(), DP_BLOCK_KEYPOINTS, atol=1e-8)


def test_reset_state_for_reproduces_an_observed_state():
    env = PushTEnv(load_task_config("pusht_state"))
    for seed in (0, 1, 2):
        state = env.reset(seed=seed)["observation"].numpy().astype(np.float64)
        raw = env.reset(options={"reset_to_state": state})["observation"].numpy()
        fixed = env.reset(options={"reset_to_state": reset_state_for(state)})["observation"].numpy()
        assert np.abs(raw[2:4] - state[2:4]).max() > 1.0  # gym-pusht's legacy setter moves the block
        np.testing.assert_allclose(fixed, state, atol=1e-4)


def test_per_env_seeded_resets_are_reproducible():
    env = PushTEnv(load_task_config("pusht_state"))
    a = env.reset(seed=5)["observation"]
    env.reset(seed=6)
    assert torch.equal(env.reset(seed=[5])["observation"], a)


def chase_block(observation: torch.Tensor) -> torch.Tensor:
    """A one-step chunk policy on the 5-D state: the agent's target is the block's position."""
    return observation[..., -1:, 2:4].clone()


def test_score_equals_diffusion_policys_metric_computed_by_hand():
    """The shared evaluator's ``score`` (from SimulatorSpec.episode_metrics) against Diffusion
    Policy's metric computed here: the episodes re-run on raw gym-pusht with the same seeds and the
    same policy, coverage recomputed from shapely polygons of the block and the goal, each episode's
    best clip(coverage / 0.95, 0, 1), then the mean over seeds."""
    import gymnasium as gym
    from l1flow_rl.envs import get_simulator, make_env
    from l1flow_rl.envs.pusht.geometry import GOAL_POSE, T_RECTANGLES, to_world
    from shapely.geometry import Polygon
    from tensordict.nn import TensorDictModule

    from l1flow_rl.evaluation import evaluate

    steps, seeds = 25, [0, 1, 2]
    env = make_env("pusht_state", num_envs=1, max_episode_steps=steps)
    policy = TensorDictModule(chase_block, in_keys=["observation"], out_keys=["action_chunk"])
    spec = get_simulator("pusht")
    result = evaluate(policy, env, episodes=len(seeds), seed=seeds[0], episode_metrics=spec.episode_metrics)
    env.close()

    goal = [Polygon(to_world(r, GOAL_POSE)) for r in T_RECTANGLES]
    goal_area = sum(g.area for g in goal)
    raw = gym.make("gym_pusht/PushT-v0", obs_type="state", disable_env_checker=True)
    by_hand = []
    for seed in seeds:
        obs, _ = raw.reset(seed=seed)
        best = 0.0
        for _ in range(steps):
            obs, *_ = raw.step(obs[2:4].astype(np.float32).astype(np.float64))
            u = raw.unwrapped
            block = [Polygon(to_world(r, [*u.block.position, u.block.angle])) for r in T_RECTANGLES]
            coverage = sum(b.intersection(g).area for b in block for g in goal) / goal_area
            best = max(best, float(np.clip(coverage / 0.95, 0.0, 1.0)))
        by_hand.append(best)
    assert [e["score"] for e in result["per_episode"]] == pytest.approx(by_hand, abs=1e-5)
    assert result["score"] == pytest.approx(np.mean(by_hand), abs=1e-5)
    assert len(set(np.round(by_hand, 3))) > 1, "the episodes should differ to test anything"
