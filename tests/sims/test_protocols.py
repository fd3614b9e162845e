"""Evaluation protocols and the validation/test split: the registry, ManiSkill's baseline settings,
command-line values recorded as deviations, seed ranges checked before any work, and
``l1flow-rl eval eval.protocol=maniskill`` on the real simulator."""

from __future__ import annotations

import dataclasses
import json

import pytest

from l1flow_rl.commands.cli import compose_config
from l1flow_rl.config import load_task_config
from l1flow_rl.config.validate import ConfigValidationError
from l1flow_rl.evaluation import EvalProtocol, get_protocol, protocol_names, register_protocol, resolve_plan
from l1flow_rl.evaluation.plan import task_from
from l1flow_rl.evaluation.protocols import _REGISTRY


def plan_for(task: str, *overrides: str):
    cfg = compose_config([f"task={task}", *overrides], command="eval")
    return resolve_plan(cfg, task_from(cfg.task), "cpu", overrides=list(overrides))


def test_default_protocol_keeps_the_task_and_splits_seeds():
    plan = plan_for("maniskill_pushcube")
    assert plan.protocol.name == "default" and plan.headline == "success_once"
    assert plan.task.max_episode_steps == 150  # the task config's own limit (demos run up to 129)
    assert plan.split("test") == (100, 100_000) and plan.split("val") == (
        20,
        10_000,
    )  # eval.val_episodes: 20 by default
    assert plan.env_device.type == "cpu" and dict(plan.protocol.env_options) == {}
    assert plan.video_episodes == 0  # videos stay off on the CPU unless asked for


@pytest.mark.parametrize(
    ("task", "steps"),
    [
        ("maniskill_pushcube", 100),
        ("maniskill_pickcube", 100),
        ("maniskill_stackcube", 200),
        ("maniskill_peginsertion", 300),
        ("maniskill_pullcube", 50),  # not in the baseline's table: PullCube-v1's registered limit
    ],
)
def test_maniskill_protocol_uses_the_baselines_settings(task, steps):
    pytest.importorskip("mani_skill")
    plan = plan_for(task, "eval.protocol=maniskill")
    assert plan.task.max_episode_steps == steps
    assert plan.episodes == 100 and plan.headline == "success_once"
    assert dict(plan.protocol.env_options) == {"reconfigure_each_episode": True}
    assert str(plan.env_device) == "cpu" and plan.deviations == []


def test_eval_env_device_picks_where_the_simulator_runs():
    # None: the protocol's (maniskill: cpu), else the run's device; given, it wins and a protocol
    # that fixes another device records the deviation.
    assert str(plan_for("maniskill_pushcube", "eval.env_device=cpu").env_device) == "cpu"
    plan = plan_for("maniskill_pushcube", "eval.protocol=maniskill", "eval.env_device=cuda")
    assert str(plan.env_device) == "cuda"
    assert plan.deviations == ["eval.env_device=cuda (protocol 'maniskill': cpu)"]
    with pytest.raises(ValueError, match=r"eval.env_device='gpu0': expected a torch device"):
        plan_for("maniskill_pushcube", "eval.env_device=gpu0")


def test_command_line_values_beat_the_protocol_and_are_recorded():
    plan = plan_for(
        "maniskill_pushcube", "eval.protocol=maniskill", "eval.episodes=3", "task.max_episode_steps=12"
    )
    assert plan.episodes == 3 and plan.task.max_episode_steps == 12
    assert plan.deviations == [
        "eval.episodes=3 (protocol 'maniskill': 100)",
        "task.max_episode_steps=12 (protocol 'maniskill': 100)",
    ]


def test_protocol_refuses_another_simulator_and_unknown_names():
    task = dataclasses.replace(load_task_config("maniskill_pushcube"), simulator="robosuite", name="x")
    with pytest.raises(
        ValueError, match=r"applies to simulators \['maniskill'\]; task 'x' runs on 'robosuite'"
    ):
        get_protocol("maniskill").eval_task(task)
    with pytest.raises(
        ValueError, match=r"unknown eval.protocol 'nope'; registered protocols: \[.*'maniskill'"
    ):
        get_protocol("nope")


def test_a_registered_protocol_is_a_valid_config_value_and_its_headline_is_checked():
    short = EvalProtocol(
        name="short_test",
        description="a test double: 4 episodes of 20 steps, seeds from 7",
        episodes=4,
        seed=7,
        task_fields=lambda task: {"max_episode_steps": 20},
        headline="return",
    )
    register_protocol(short)
    try:
        assert "short_test" in protocol_names()
        with pytest.raises(ValueError, match="already registered"):
            register_protocol(dataclasses.replace(short, episodes=5))
        plan = plan_for("maniskill_pushcube", "eval.protocol=short_test")
        assert (plan.episodes, plan.seed, plan.task.max_episode_steps, plan.headline) == (4, 7, 20, "return")
        register_protocol(dataclasses.replace(short, headline="coverage"), replace=True)
        with pytest.raises(
            ValueError, match=r"reports 'coverage' first, but simulator 'maniskill' yields only"
        ):
            plan_for("maniskill_pushcube", "eval.protocol=short_test")
    finally:
        _REGISTRY.pop("short_test", None)


def test_bad_protocol_and_overlapping_seeds_fail_when_the_config_is_composed():
    with pytest.raises(ConfigValidationError, match=r"eval.protocol='nope'"):
        compose_config(["eval.protocol=nope"], command="train")
    with pytest.raises(
        ConfigValidationError, match=r"eval.val_seed=100010 \(\+20 episodes\) overlaps the test seeds"
    ):
        compose_config(["eval.val_seed=100010"], command="train")
    compose_config(["eval.val_seed=100100"], command="train")  # adjacent ranges are fine (100 test episodes)


@pytest.mark.maniskill
def test_cli_eval_under_the_maniskill_protocol_writes_what_it_did(tmp_path):
    pytest.importorskip("mani_skill")
    from omegaconf import OmegaConf

    from l1flow_rl.commands.cli import main
    from l1flow_rl.workspace.build import build_actor
    from l1flow_rl.workspace.checkpoint import save_checkpoint

    cfg = compose_config(["network.down_dims=[16,32]", "network.timestep_embed_dim=16"])
    actor = build_actor(cfg.policy, {"state": (35,)}, 4, None, cfg.network)
    state = {"model": actor.state_dict(), "ema": None, "config": OmegaConf.to_container(cfg, resolve=True)}
    path = save_checkpoint(tmp_path / "ck.pt", {**state, "obs_shapes": {"state": [35]}, "action_dim": 4})
    run_dir = tmp_path / "run"
    args = [f"checkpoint={path}", f"run_dir={run_dir}", "device=cpu", "eval.num_envs=1"]
    args += ["eval.protocol=maniskill", "eval.episodes=2", "task.max_episode_steps=6"]
    assert main(["eval", *args]) == 0
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["split"] == "test" and result["split_seeds"] == {"first": 100_000, "episodes": 2}
    assert [e["seed"] for e in result["per_episode"]] == [100_000, 100_001]
    protocol = result["protocol"]
    assert protocol["name"] == "maniskill" and protocol["env_options"] == {"reconfigure_each_episode": True}
    assert protocol["env_device"] == "cpu" and protocol["max_episode_steps"] == 6
    assert len(protocol["deviations"]) == 2
    assert result["headline"]["metric"] == "success_once"
    assert result["headline"]["value"] == result["success_once"]
    # an untrained policy fails both episodes: the Wilson interval of 0/2 is [0, z^2 / (2 + z^2)]
    assert result["success_once"] == 0.0
    assert result["ci95"]["success_once"] == pytest.approx([0.0, 3.8415 / 5.8415], abs=1e-4)
    assert result["ci_method"] == {
        "success_once": "wilson",
        "success_at_end": "wilson",
        "return": "t",
        "episode_length": "t",
    }
    assert [e["length"] for e in result["per_episode"]] == [6, 6]
