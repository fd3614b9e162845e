"""A new simulator added without touching make_env, the trainer or the evaluator: the point-mass
double (tests/doubles/point_mass) registers itself and its expert, then runs through make_env,
``l1flow_rl.evaluate`` and the whole ``l1flow-rl train`` command."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
from doubles.point_mass import POINT_MASS_TASK, TASK_OVERRIDES, PointMassEnv
from doubles.point_mass.env import OBS_DIM, episode_start, expert_action
from l1flow_rl.envs import get_simulator, make_env
from l1flow_rl.envs.contract import ContractError, check_env_contract
from l1flow_rl.envs.per_env import render_frames, seeded_reset
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import check_env_specs, step_mdp

from l1flow_rl import evaluate

CHUNK = 4


def test_make_env_stacks_history_and_resets_per_env_from_seeds():
    env = make_env(POINT_MASS_TASK, num_envs=2, obs_horizon=3)
    check_env_specs(env)
    td = seeded_reset(env, None, [11, 12])
    obs = td["observation"]
    assert obs.shape == (2, 3, OBS_DIM) and td["is_init"].all()
    assert torch.equal(obs[:, 0], obs[:, 2])  # padded with copies of the first observation
    start, goal = episode_start(11)
    assert torch.allclose(obs[0, -1], torch.cat([start, torch.zeros(2), goal]))
    fresh = obs.clone()

    td["action"] = torch.ones(2, 2)
    td = step_mdp(env.step(td))
    assert torch.equal(td["observation"][:, 1], fresh[:, 2])  # the history shifts by one frame
    assert not torch.equal(td["observation"][:, 2], fresh[:, 2])
    moved = td["observation"].clone()

    td = seeded_reset(env, td, [None, 11])  # env 1 starts seed 11's episode, env 0 goes on
    assert td["is_init"].squeeze(-1).tolist() == [False, True]
    assert torch.equal(td["observation"][0], moved[0])
    assert torch.equal(td["observation"][1], fresh[0])
    frames = render_frames(env)
    assert frames.shape == (2, 32, 32, 3) and frames.dtype == torch.uint8


def test_the_time_limit_truncates_and_success_terminates_only_when_asked():
    task = dataclasses.replace(POINT_MASS_TASK, max_episode_steps=5)
    rollout = make_env(task, num_envs=2).rollout(20, break_when_any_done=True)
    assert rollout.batch_size == (2, 5)
    assert rollout["next", "truncated"][:, -1].all() and not rollout["next", "terminated"].any()

    env = make_env(POINT_MASS_TASK, ignore_terminations=False)
    policy = TensorDictModule(lambda obs: expert_action(obs[..., -1, :]), ["observation"], ["action"])
    env.set_seed(0)
    run = env.rollout(30, policy, break_when_any_done=True)[0]
    assert run["next", "terminated"][-1].item() and run["next", "success"][-1].item()
    assert not run["next", "success"][:-1].any() and len(run) < 30


def expert_chunks() -> TensorDictModule:
    """The expert's action at the chunk's first step, held for the whole chunk."""

    def chunk(observation: torch.Tensor) -> torch.Tensor:
        action = expert_action(observation[..., -1, :])
        return action.unsqueeze(-2).expand(*action.shape[:-1], CHUNK, 2).clone()

    return TensorDictModule(chunk, in_keys=["observation"], out_keys=["action_chunk"])


def by_hand(seed: int) -> dict:
    """One episode on a bare PointMassEnv, stepped here: the numbers evaluate() must report."""
    env = PointMassEnv(POINT_MASS_TASK, num_envs=1)
    td = env.reset(seed=[seed])
    ret, successes, action = 0.0, [], None
    for t in range(POINT_MASS_TASK.max_episode_steps):
        if t % CHUNK == 0:
            action = expert_action(td["observation"])
        td["action"] = action
        td = env.step(td)
        ret += td["next", "reward"].item()
        successes.append(td["next", "success"].item())
        distance = td["next", "distance"].item()
        done = td["next", "done"].item()
        td = step_mdp(td)
        if done:
            break
    return {
        "seed": seed,
        "success_once": any(successes),
        "success_at_end": successes[-1],
        "return": ret,
        "length": len(successes),
        "final_distance": distance,
    }


def test_evaluate_runs_the_double_and_its_metrics_equal_counts_by_hand():
    env = make_env(POINT_MASS_TASK, num_envs=2)
    metrics = get_simulator("point_mass").episode_metrics
    result = evaluate(expert_chunks(), env, episodes=5, seed=3, episode_metrics=metrics)
    want = [by_hand(seed) for seed in range(3, 8)]
    got = result["per_episode"]
    assert [e["seed"] for e in got] == [3, 4, 5, 6, 7]
    for g, w in zip(got, want):
        assert (g["success_once"], g["success_at_end"], g["length"]) == (
            w["success_once"],
            w["success_at_end"],
            w["length"],
        ), g["seed"]
        assert g["return"] == pytest.approx(w["return"], rel=1e-5)
        assert g["final_distance"] == pytest.approx(w["final_distance"], rel=1e-5)
    assert result["episodes"] == 5 and result["errors"] == 0
    assert result["success_once"] == pytest.approx(sum(w["success_once"] for w in want) / 5)
    assert result["final_distance"] == pytest.approx(sum(w["final_distance"] for w in want) / 5, rel=1e-5)
    assert any(w["success_once"] for w in want), "the expert should reach some goals"


def test_l1flow_rl_train_on_the_double_writes_eval_json(tmp_path):
    from l1flow_rl.commands.cli import main

    run_dir, data_dir = tmp_path / "run", tmp_path / "data"
    args = [
        *TASK_OVERRIDES,
        "demos.num=4",
        "train.steps=20",
        "train.batch_size=16",
        "train.warmup_steps=2",
        "eval.episodes=2",
        "eval.num_envs=2",
        "network.down_dims=[16,32]",
        "device=cpu",
        f"data_dir={data_dir}",
        f"run_dir={run_dir}",
    ]
    assert main(["train", *args]) == 0
    demos = sorted((data_dir / "point_mass").glob("*.hdf5"))
    assert [p.name for p in demos] == ["PointMassReach-v0_normalized_dense_seed0_n4.hdf5"]
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["episodes"] == 2 and len(result["per_episode"]) == 2
    assert all(e["length"] == 30 for e in result["per_episode"])  # every episode runs to the time limit
    assert 0.0 <= result["success_once"] <= 1.0
    assert "final_distance" in result  # the double's own episode metric reached eval.json
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["task"] == "point_mass_reach" and summary["steps"] == 20

    # ... and `l1flow-rl eval` re-scores the checkpoint on the double
    eval_dir = tmp_path / "eval"
    checkpoint = run_dir / "checkpoints" / "best.pt"
    args = [*TASK_OVERRIDES, f"checkpoint={checkpoint}", "eval.episodes=3", f"run_dir={eval_dir}"]
    assert main(["eval", *args]) == 0
    rescored = json.loads((eval_dir / "eval.json").read_text())
    assert rescored["episodes"] == 3 and [e["length"] for e in rescored["per_episode"]] == [30, 30, 30]


@pytest.mark.parametrize("num_envs", [1, 3])
def test_the_double_honours_the_env_contract(num_envs):
    check_env_contract(make_env(POINT_MASS_TASK, num_envs=num_envs))


class ForgetsSeeds(PointMassEnv):
    """Ignores reset seeds: every reset draws a fresh episode."""

    def _reset(self, tensordict=None, *, seed=None, **kwargs):
        return super()._reset(tensordict, seed=None, **kwargs)


class ResetsEveryEnv(PointMassEnv):
    """Ignores the "_reset" mask: a partial reset restarts every env."""

    def _reset(self, tensordict=None, *, seed=None, **kwargs):
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is not None and not mask.all():  # env 0 from its seed, the others from seed 999
            return super()._reset(None, seed=[int(seed[0])] + [999] * (self.num_envs - 1), **kwargs)
        return super()._reset(tensordict, seed=seed, **kwargs)


@pytest.mark.parametrize(
    ("env_class", "message"),
    [
        (ForgetsSeeds, r"reset\(seed=\[3, 4\]\) twice gave different observations"),
        (ResetsEveryEnv, "restarted or changed the envs it did not name"),
    ],
)
def test_the_contract_check_names_a_broken_reset(env_class, message):
    from l1flow_rl.envs.factory import history_transforms
    from torchrl.envs import TransformedEnv

    env = TransformedEnv(env_class(POINT_MASS_TASK, 2), history_transforms({"observation": 1}, 2))
    with pytest.raises(ContractError, match=message):
        check_env_contract(env)
