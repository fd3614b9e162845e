"""The evaluator's success_once, success_at_end, return and length equal ManiSkill's own episode
metrics (``ManiSkillVectorEnv(record_metrics=True)``, what ManiSkill's baselines report) on the same
seeds, with the same scripted policy run on the raw ManiSkill env."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

pytest.importorskip("mani_skill")

from l1flow_rl.envs import make_env
from tensordict.nn import TensorDictModule

from l1flow_rl import evaluate

pytestmark = pytest.mark.maniskill

CHUNK, STEPS, SEED, EPISODES = 4, 40, 20, 4


def pusher_chunk(history: torch.Tensor) -> torch.Tensor:
    """[..., To, 35] PushCube states -> [..., CHUNK, 4]: move behind the cube, then push it to the
    goal (tcp_pose 18:21, goal_pos 25:28, obj_pose 28:31), easing off along the chunk."""
    obs = history[..., -1, :]
    tcp, goal, cube = obs[..., 18:21], obs[..., 25:28], obs[..., 28:31]
    behind = cube + torch.tensor([-0.05, 0.0, 0.0])
    behind[..., 2] = 0.02
    aligned = ((tcp[..., 1:2] - cube[..., 1:2]).abs() < 0.01) & (tcp[..., 0:1] < cube[..., 0:1] - 0.03)
    target = torch.where(aligned, goal + torch.tensor([0.0, 0.0, 0.02]), behind)
    move = ((target - tcp) * 10).clamp(-1, 1)
    ease = 1.0 - 0.1 * torch.arange(CHUNK, dtype=torch.float32).unsqueeze(-1)  # [CHUNK, 1]
    chunk = torch.cat([move.unsqueeze(-2) * ease, -torch.ones(*move.shape[:-1], CHUNK, 1)], -1)
    return chunk


def maniskill_metrics(seed: int, venv) -> dict:
    """One episode on ManiSkill's own vector env, the policy fed from ManiSkill's observations."""
    obs, _ = venv.reset(seed=seed, options={"reconfigure": True})
    history = [obs[0], obs[0]]  # To = 2, padded at reset like the history transforms
    for t in range(STEPS + 1):
        if t % CHUNK == 0:
            chunk = pusher_chunk(torch.stack(history).float())
        obs, _, _, truncated, info = venv.step(chunk[t % CHUNK].unsqueeze(0))
        history = [history[-1], obs[0]]
        if bool(truncated.any()):
            break
    episode = info["episode"]
    return {
        "success_once": bool(episode["success_once"].item()),
        "success_at_end": bool(episode["success_at_end"].item()),
        "return": float(episode["return"].item()),
        "length": int(episode["episode_len"].item()),
    }


def test_evaluator_metrics_equal_maniskill_record_metrics():
    from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

    # Rebuilding the scene at every reset (both sides) makes an episode depend on its seed alone.
    env = make_env("maniskill_pushcube", max_episode_steps=STEPS, reconfigure_each_episode=True, render=False)
    policy = TensorDictModule(pusher_chunk, in_keys=["observation"], out_keys=["action_chunk"])
    try:
        ours = evaluate(policy, env, episodes=EPISODES, seed=SEED)["per_episode"]
    finally:
        env.close()

    raw = gym.make(
        "PushCube-v1",
        num_envs=1,
        obs_mode="state",
        control_mode="pd_ee_delta_pos",
        reward_mode="normalized_dense",
        max_episode_steps=STEPS,
        sim_backend="physx_cpu",
        render_backend="cpu",
    )
    venv = ManiSkillVectorEnv(raw, ignore_terminations=True, record_metrics=True, auto_reset=False)
    try:
        theirs = [maniskill_metrics(SEED + i, venv) for i in range(EPISODES)]
    finally:
        venv.close()

    assert [e["seed"] for e in ours] == list(range(SEED, SEED + EPISODES))
    for got, want in zip(ours, theirs):
        assert (got["success_once"], got["success_at_end"], got["length"]) == (
            want["success_once"],
            want["success_at_end"],
            want["length"],
        ), got["seed"]
        assert got["return"] == pytest.approx(want["return"], rel=1e-5, abs=1e-5), got["seed"]
    assert all(e["length"] == STEPS for e in theirs)
    # the episodes tell the metrics apart: some succeed, and success_once differs from success_at_end
    once = np.array([e["success_once"] for e in theirs])
    at_end = np.array([e["success_at_end"] for e in theirs])
    assert once.any() and (once != at_end).any(), theirs
