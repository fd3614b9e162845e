"""The CLI's config layer: composition, validation before any work, --cfg job and --help."""

from __future__ import annotations

import pytest

from l1flow_rl.cli import COMMANDS, compose_config, main
from l1flow_rl.config import load_task_config, task_names


def test_default_config_is_the_main_job():
    cfg = compose_config([])
    assert cfg.task.name == "maniskill_pushcube"
    assert cfg.task.obs_mode == "state"
    assert cfg.policy.name == "l1flow"
    assert cfg.policy.sampler == "two_step"
    assert cfg.policy.sampler_kwargs.t_first == 0.5
    assert cfg.demos.num == 100
    assert list(cfg.train.betas) == [0.95, 0.999]
    assert cfg.train.weight_decay == 1e-6
    assert cfg.train.ema_power == 0.75
    assert cfg.eval.episodes >= 50


def test_paper_training_preset():
    cfg = compose_config(["train=paper"])
    assert cfg.train.lr == 1e-4
    assert cfg.train.warmup_steps == 500
    assert cfg.train.batch_size == 64
    assert list(cfg.train.betas) == [0.95, 0.999]
    assert cfg.run_dir.startswith("runs/maniskill_pushcube_l1flow/")


@pytest.mark.parametrize("policy", ["l1flow", "flow", "ddpm", "ddim", "regression"])
def test_every_policy_config_composes(policy):
    cfg = compose_config([f"policy={policy}", "train.steps=7"])
    assert cfg.policy.name == policy
    assert cfg.train.steps == 7


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("train.stepz=3", "stepz"),
        ("train.steps=abc", "train.steps"),
        ("task=no_such_task", "task/no_such_task"),
        ("policy.down_dims=12", "policy.down_dims"),
        ("eval.episodes=[1]", "eval.episodes"),
    ],
)
def test_bad_override_fails_before_work_and_names_the_key(override, message, capsys):
    assert main(["train", override]) == 2
    err = capsys.readouterr().err
    assert "invalid config" in err
    assert message in err


def test_cfg_job_prints_composed_config(capsys):
    assert main(["train", "policy=ddim", "train.steps=11", "--cfg", "job"]) == 0
    out = capsys.readouterr().out
    assert "sampler: ddim" in out
    assert "steps: 11" in out


def test_help_lists_every_subcommand(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert f"  {name} " in out
    assert main(["frobnicate"]) == 2


def test_task_configs_are_valid_and_fit_their_demos():
    names = task_names()
    for required in (
        "maniskill_pushcube",
        "maniskill_pickcube",
        "maniskill_stackcube",
        "maniskill_peginsertion",
        "maniskill_pickcube_rgb",
    ):
        assert required in names
    for name in names:
        task = load_task_config(name)
        assert task.name == name
        # ManiSkill's default limits cut demonstrations short (PickCube demos need 74-88 steps).
        assert task.max_episode_steps >= 100
    with pytest.raises(ValueError, match="unknown task 'nope'"):
        load_task_config("nope")
