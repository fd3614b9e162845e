"""The evaluator on the real ManiSkill simulator (PushCube, physx_cpu) with a scripted chunk policy:
metrics equal counts taken by hand, errors are recorded rather than fatal, videos, and the CLI."""

import json

import gymnasium as gym
import numpy as np
import pytest
import torch

pytest.importorskip("mani_skill")

from l1flow_rl.envs import history_transforms, make_env
from l1flow_rl.envs.maniskill.async_env import ManiSkillAsyncEnv
from l1flow_rl.envs.maniskill.env import ManiSkillEnv
from tensordict.nn import TensorDictModule
from torchrl.envs import Transform, TransformedEnv
from torchrl.modules import MultiStepActorWrapper

from l1flow_rl import evaluate
from l1flow_rl.config import load_task_config

pytestmark = pytest.mark.maniskill

CHUNK = 4
STEPS = 30


def push_chunk(observation: torch.Tensor) -> torch.Tensor:
    """Scripted PushCube pusher: get behind the cube, then push it towards the goal (state layout:
    tcp_pose 18:25, goal_pos 25:28, obj_pose 28:35); the same action repeated over the chunk."""
    obs = observation[..., -1, :]
    tcp, goal, cube = obs[..., 18:21], obs[..., 25:28], obs[..., 28:31]
    behind = cube + torch.tensor([-0.05, 0.0, 0.0])
    behind[..., 2] = 0.02
    aligned = ((tcp[..., 1:2] - cube[..., 1:2]).abs() < 0.01) & (tcp[..., 0:1] < cube[..., 0:1] - 0.03)
    target = torch.where(aligned, goal + torch.tensor([0.0, 0.0, 0.02]), behind)
    action = torch.cat([((target - tcp) * 10).clamp(-1, 1), -torch.ones_like(tcp[..., :1])], -1)
    return action.unsqueeze(-2).expand(*action.shape[:-1], CHUNK, 4).clone()


def scripted_policy() -> TensorDictModule:
    return TensorDictModule(push_chunk, in_keys=["observation"], out_keys=["action_chunk"])


def evaluate_then_close(env, episodes: int) -> dict:
    try:
        return evaluate(scripted_policy(), env, episodes=episodes, seed=0)
    finally:
        env.close()


@pytest.fixture(scope="module")
def env():
    # Rebuilding the scene at each reset makes an episode depend on its seed alone (PhysX carries
    # solver state across plain resets), so episodes can be compared across envs and orders.
    env = make_env("maniskill_pushcube", max_episode_steps=STEPS, reconfigure_each_episode=True)
    yield env
    env.close()


def test_metrics_equal_counts_by_hand(env):
    result = evaluate(scripted_policy(), env, episodes=4, seed=0)

    executor = MultiStepActorWrapper(scripted_policy(), n_steps=CHUNK)
    by_hand = []
    for seed in range(4):
        start = env.reset(seed=[seed])
        rollout = env.rollout(STEPS + 10, executor, auto_reset=False, tensordict=start)[0]
        success = rollout["next", "success"].squeeze(-1)
        by_hand.append(
            {
                "seed": seed,
                "success_once": bool(success.any()),
                "success_at_end": bool(success[-1]),
                # 1-based step of the first success, None for an episode that never succeeds
                "first_success_step": int(success.nonzero()[0, 0]) + 1 if success.any() else None,
                "return": rollout["next", "reward"].sum().item(),
                "length": rollout.shape[0],
            }
        )
    episodes = result["per_episode"]
    assert [e["seed"] for e in episodes] == [0, 1, 2, 3]
    for got, want in zip(episodes, by_hand):
        assert (got["success_once"], got["success_at_end"], got["length"]) == (
            want["success_once"],
            want["success_at_end"],
            want["length"],
        )
        assert got["first_success_step"] == want["first_success_step"]
        assert got["return"] == pytest.approx(want["return"], rel=1e-5)
        assert got["error"] is None
    assert any(e["success_once"] for e in by_hand), "the scripted pusher should solve some episodes"
    assert any(e["success_once"] != e["success_at_end"] for e in by_hand), (
        "no episode tells the metrics apart"
    )
    assert any(1 < (e["first_success_step"] or 0) < STEPS for e in by_hand), "no success inside the episode"
    n = len(by_hand)
    assert result["episodes"] == n and result["errors"] == 0
    assert result["success_once"] == pytest.approx(sum(e["success_once"] for e in by_hand) / n)
    assert result["success_at_end"] == pytest.approx(sum(e["success_at_end"] for e in by_hand) / n)
    assert result["return"] == pytest.approx(sum(e["return"] for e in by_hand) / n, rel=1e-5)
    assert result["episode_length"] == STEPS
    # one policy call per chunk: ceil(30 / 4) = 8 per episode
    assert result["policy_calls"] == 4 * 8
    assert 0 < result["latency_ms_median"] <= result["latency_ms_p90"]


def test_two_workers_run_the_same_seeded_episodes(env):
    one = evaluate(scripted_policy(), env, episodes=3, seed=10)
    two_env = make_env(
        "maniskill_pushcube", num_envs=2, max_episode_steps=STEPS, reconfigure_each_episode=True
    )
    try:
        two = evaluate(scripted_policy(), two_env, episodes=3, seed=10)
    finally:
        two_env.close()
    assert [e["seed"] for e in two["per_episode"]] == [10, 11, 12]
    for a, b in zip(one["per_episode"], two["per_episode"]):
        for key in ("seed", "success_once", "success_at_end", "length"):
            assert a[key] == b[key], key
        assert a["return"] == pytest.approx(b["return"], rel=1e-5)
    # the third episode runs on one worker while the other idles; calls are batched over both
    assert (one["policy_calls"], two["policy_calls"]) == (3 * 8, 2 * 8)


def test_noise_seed_changes_the_policy_noise_and_keeps_the_episodes(env):
    # a pusher with sampled noise on its actions (drawn from the global RNG that evaluate seeds)
    def noisy_chunk(observation: torch.Tensor) -> torch.Tensor:
        chunk = push_chunk(observation)
        return chunk + 0.5 * torch.randn_like(chunk)

    noisy = TensorDictModule(noisy_chunk, in_keys=["observation"], out_keys=["action_chunk"])
    default = evaluate(noisy, env, episodes=2, seed=0)
    same = evaluate(noisy, env, episodes=2, seed=0, noise_seed=0)
    other = evaluate(noisy, env, episodes=2, seed=0, noise_seed=1)
    returns = lambda r: [e["return"] for e in r["per_episode"]]  # noqa: E731
    assert returns(default) == returns(same)
    assert [e["seed"] for e in other["per_episode"]] == [0, 1]
    assert all(a != b for a, b in zip(returns(default), returns(other)))


class RaiseAtStep(Transform):
    """Raises from inside env.step on its n-th call, once (e.g. a sensor or a transform failing)."""

    def __init__(self, at: int) -> None:
        super().__init__()
        self.at, self.calls = at, 0

    def _step(self, tensordict, next_tensordict):
        self.calls += 1
        if self.calls == self.at:
            raise RuntimeError("transform failed on purpose")
        return next_tensordict


def test_an_env_that_raises_is_recorded_and_evaluation_goes_on():
    env = make_env("maniskill_pushcube", max_episode_steps=STEPS)
    env.append_transform(RaiseAtStep(at=STEPS + 5))  # during the second episode
    result = evaluate_then_close(env, episodes=3)
    episodes = result["per_episode"]
    assert [e["seed"] for e in episodes] == [0, 1, 2]
    assert episodes[1]["error"] == "RuntimeError: transform failed on purpose"
    assert not episodes[1]["success_once"] and episodes[1]["length"] == 4
    assert episodes[0]["error"] is None and episodes[2]["error"] is None
    assert episodes[2]["length"] == STEPS
    assert result["errors"] == 1 and result["episodes"] == 3


class PhysxFails(gym.Wrapper):
    def __init__(self, env, at: int) -> None:
        super().__init__(env)
        self.at, self.steps = at, 0

    def step(self, action):
        self.steps += 1
        if self.steps == self.at:
            raise RuntimeError("PhysX: simulation blew up")
        return self.env.step(action)


class FlakyManiSkillEnv(ManiSkillEnv):
    """The real simulator, whose first instance raises at its third step."""

    sims_made = 0

    def _make_sim(self):
        sim = super()._make_sim()
        FlakyManiSkillEnv.sims_made += 1
        return PhysxFails(sim, at=3) if FlakyManiSkillEnv.sims_made == 1 else sim


def test_a_simulator_error_ends_that_episode_and_the_simulator_is_rebuilt():
    task = load_task_config("maniskill_pushcube", max_episode_steps=6)
    env = TransformedEnv(FlakyManiSkillEnv(task), history_transforms({"observation": 1}, 2))
    result = evaluate_then_close(env, 2)
    first, second = result["per_episode"]
    assert first["error"] == "RuntimeError: PhysX: simulation blew up"
    assert first["length"] == 2 and not first["success_once"]
    assert second["error"] is None and second["length"] == 6
    assert FlakyManiSkillEnv.sims_made == 2


FAIL_SEED = 1


class PhysxFailsOnSeed(gym.Wrapper):
    """Raises at the third step of the episode seeded FAIL_SEED."""

    def reset(self, **kwargs):
        self.steps = 0
        return self.env.reset(**kwargs)

    def step(self, action):
        self.steps += 1
        seed = int(np.asarray(self.env.unwrapped._episode_seed).reshape(-1)[0])
        if self.steps == 3 and seed == FAIL_SEED:
            raise RuntimeError("PhysX: simulation blew up")
        return self.env.step(action)


class SeedFailingManiSkillEnv(ManiSkillEnv):
    """Module-level, so that worker processes unpickle it by reference."""

    def _make_sim(self):
        return PhysxFailsOnSeed(super()._make_sim())


def test_a_worker_whose_simulator_raises_is_rebuilt_while_the_other_goes_on():
    task = load_task_config("maniskill_pushcube", max_episode_steps=6)
    base = ManiSkillAsyncEnv(task, 2, worker_env=SeedFailingManiSkillEnv)
    result = evaluate_then_close(TransformedEnv(base, history_transforms({"observation": 1}, 2)), 3)
    episodes = result["per_episode"]
    assert [e["seed"] for e in episodes] == [0, 1, 2]
    # worker 1 fails in seed 1's episode and is rebuilt for seed 2's while worker 0 runs on
    assert episodes[1]["error"] == "RuntimeError: PhysX: simulation blew up"
    assert episodes[1]["length"] == 2 and not episodes[1]["success_once"]
    assert [episodes[0]["error"], episodes[2]["error"]] == [None, None]
    assert episodes[0]["length"] == episodes[2]["length"] == 6
    assert result["errors"] == 1


def test_video_of_the_first_episode(tmp_path):
    import imageio.v3 as iio

    env = make_env("maniskill_pushcube", max_episode_steps=3)
    try:
        result = evaluate(scripted_policy(), env, episodes=2, seed=0, video_dir=tmp_path, video_episodes=1)
    finally:
        env.close()
    videos = sorted(tmp_path.glob("*.mp4"))
    assert [v.name for v in videos] == ["episode000_seed0.mp4"]
    assert result["per_episode"][0]["video"] == str(videos[0])
    frames = iio.imread(videos[0])
    assert frames.shape[0] == 4 and frames.shape[-1] == 3  # the reset frame and one per step


def test_cli_eval_writes_eval_json(tmp_path):
    from omegaconf import OmegaConf

    from l1flow_rl.commands.cli import compose_config, main
    from l1flow_rl.workspace.build import build_actor
    from l1flow_rl.workspace.checkpoint import save_checkpoint

    cfg = compose_config(["network.down_dims=[16,32]", "network.timestep_embed_dim=16"])
    actor = build_actor(cfg.policy, {"state": (35,)}, 4, None, cfg.network)
    path = save_checkpoint(
        tmp_path / "ck.pt",
        {
            "model": actor.state_dict(),
            "ema": None,
            "config": OmegaConf.to_container(cfg, resolve=True),
            "obs_shapes": {"state": [35]},
            "action_dim": 4,
        },
    )
    run_dir = tmp_path / "run"
    args = [f"checkpoint={path}", "eval.episodes=2", "eval.num_envs=1", f"run_dir={run_dir}", "device=cpu"]
    assert main(["eval", *args, "task.max_episode_steps=10"]) == 0
    written = json.loads((run_dir / "eval.json").read_text())
    assert written["episodes"] == 2 and written["task"] == "maniskill_pushcube"
    assert {"success_once", "success_at_end", "return", "latency_ms_median", "per_episode"} <= set(written)
    assert [e["length"] for e in written["per_episode"]] == [10, 10]


def test_videos_without_an_mp4_writer_are_refused_before_any_episode(monkeypatch, tmp_path):
    # Without imageio-ffmpeg, imageio hands a .mp4 to another plugin that fails only when the first
    # video is written (seen on a GPU machine: "TiffWriter.write() got an unexpected keyword 'fps'",
    # after the whole training). The plan decides up front.
    from l1flow_rl.evaluation import videos

    assert videos.video_episodes_to_film(None, "cpu") == 0  # no videos by default on the CPU
    assert videos.video_episodes_to_film(3, "cpu") == 3  # imageio-ffmpeg is installed here
    monkeypatch.setattr(videos, "_has_mp4_writer", lambda: False)
    with pytest.raises(ValueError, match=r"eval.video_episodes=2: .*pip install imageio-ffmpeg"):
        videos.video_episodes_to_film(2, "cpu")
    assert videos.video_episodes_to_film(0, "cpu") == 0
    with pytest.warns(UserWarning, match="imageio-ffmpeg"):
        assert videos.video_episodes_to_film(None, torch.device("cuda")) == 0  # the GPU default, dropped
    with pytest.raises(ImportError, match="imageio-ffmpeg"):
        videos.write_video(tmp_path / "v.mp4", [np.zeros((8, 8, 3), np.uint8)], fps=10)
    assert not (tmp_path / "v.mp4").exists()
