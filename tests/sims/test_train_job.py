"""``l1flow-rl train`` end to end on the real ManiSkill simulator, with tiny budgets."""

from __future__ import annotations

import json
import re

import pytest
import torch

pytest.importorskip("mani_skill", reason="needs ManiSkill: pip install 'l1flow-rl[maniskill]'")

from l1flow_rl.commands.cli import main
from l1flow_rl.workspace.checkpoint import ResumeMismatchError, load_checkpoint
from l1flow_rl.workspace.trainer import Trainer

pytestmark = pytest.mark.maniskill

TINY = [
    "demos.num=3",
    "train.steps=40",
    "train.checkpoint_every=20",
    "train.batch_size=32",
    "train.log_every=1",
    "train.warmup_steps=5",
    "train.lr=1e-3",
    "network.down_dims=[16,32]",
    "network.timestep_embed_dim=16",
    "eval.episodes=2",
    "eval.num_envs=1",
    "task.max_episode_steps=30",
]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("demos")


@pytest.fixture(scope="module")
def full_run(tmp_path_factory, data_dir):
    run_dir = tmp_path_factory.mktemp("full") / "run"
    assert main(["train", f"data_dir={data_dir}", f"run_dir={run_dir}", *TINY]) == 0
    return run_dir


def _tensors_equal(a: dict, b: dict) -> list[str]:
    return [k for k in a if not torch.equal(a[k], b[k])]


def test_train_writes_checkpoints_eval_and_plots(full_run):
    result = json.loads((full_run / "eval.json").read_text())
    assert result["episodes"] == 2
    assert 0.0 <= result["success_at_end"] <= result["success_once"] <= 1.0
    for name in ("latest.pt", "best.pt"):
        raw = torch.load(full_run / "checkpoints" / name, weights_only=True)
        assert raw["step"] == 40
        assert {"model", "ema", "optimizer", "scheduler", "config", "rng", "sampler_rng"} <= set(raw)
    assert (full_run / "loss.png").stat().st_size > 1000
    assert (full_run / "success.png").stat().st_size > 1000
    # the test row names the weights it scored and their interval (the plot draws it there)
    (test_row,) = [
        e for e in json.loads((full_run / "history.json").read_text())["evals"] if e["split"] == "test"
    ]
    assert test_row["weights_step"] == result["selection"]["step"]
    low, high = test_row["ci95"]["success_once"]
    assert low <= test_row["success_once"] == result["success_once"] <= high
    assert (full_run / "config.yaml").is_file()
    assert list((full_run / "logs").rglob("*.csv")), "the CSV logger wrote nothing"


def test_train_cuts_the_loss_by_a_stated_factor(full_run):
    # 3 demonstrations, 40 steps at lr 1e-3: the mean loss of the last 5 steps falls below 0.65x that
    # of the first 3 (measured 0.46-0.49x over seeds 0-2).
    history = load_checkpoint(full_run / "checkpoints" / "latest.pt")["history"]
    assert history["step"] == list(range(1, 41))
    losses = history["loss"]
    start, end = sum(losses[:3]) / 3, sum(losses[-5:]) / 5
    assert end < 0.65 * start, f"loss {start:.4f} -> {end:.4f} ({end / start:.2f}x)"


def test_train_run_records_its_config_and_overrides(full_run):
    import yaml

    recorded = yaml.safe_load((full_run / ".hydra" / "overrides.yaml").read_text())
    assert "train.steps=40" in recorded and f"run_dir={full_run}" in recorded
    assert yaml.safe_load((full_run / ".hydra" / "config.yaml").read_text())["train"]["steps"] == 40


def test_crash_keeps_last_checkpoint_and_resume_matches_uninterrupted_run(
    tmp_path, data_dir, full_run, monkeypatch, capsys
):
    run_dir = tmp_path / "run"
    real_step = Trainer.train_step

    def crashing_step(self, batch):
        if self.step == 30:
            raise RuntimeError("simulated crash at step 30")
        return real_step(self, batch)

    monkeypatch.setattr(Trainer, "train_step", crashing_step)
    with pytest.raises(RuntimeError, match="simulated crash"):
        main(["train", f"data_dir={data_dir}", f"run_dir={run_dir}", *TINY])
    crashed = load_checkpoint(run_dir / "checkpoints")
    assert crashed["step"] == 20  # the last good one, intact
    assert crashed["elapsed"]["since_step"] == 0 and crashed["elapsed"]["train"] > 0
    monkeypatch.setattr(Trainer, "train_step", real_step)

    # Errors the user can fix: one message on stderr, exit code 2 (the CLI decides by type).
    capsys.readouterr()
    assert main(["train", f"data_dir={data_dir}", f"run_dir={run_dir}", *TINY]) == 2
    assert "already holds a run" in capsys.readouterr().err
    base = ["train", f"data_dir={data_dir}", f"run_dir={run_dir}", *TINY, "resume=true"]
    for change, field in [
        ("network.down_dims=[16,64]", r"network\.down_dims"),  # the network
        ("train.steps=50", r"train\.steps: checkpoint has 40, config asks for 50"),  # the schedule
        ("demos.num=4", r"demos\.num: checkpoint has 3, config asks for 4"),  # the dataset
        ("policy.loss_kwargs.loss_type=mse", r"policy\.loss_kwargs\.loss_type"),  # the loss
    ]:
        assert main([*base, change]) == 2
        assert re.search(rf"^l1flow-rl train: resume=true: .*\n(  .*\n)*  {field}", capsys.readouterr().err)
        with pytest.raises(ResumeMismatchError, match=field):  # the type the CLI decided by
            main(["--debug", *base, change])
        capsys.readouterr()

    # Checkpoint cadence may change on resume; the result is still the uninterrupted run's.
    assert main([*base, "train.checkpoint_every=10"]) == 0
    resumed = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    straight = load_checkpoint(full_run / "checkpoints" / "latest.pt")
    assert resumed["step"] == straight["step"] == 40
    assert _tensors_equal(resumed["model"], straight["model"]) == []
    assert _tensors_equal(resumed["ema"], straight["ema"]) == []
    assert resumed["history"]["loss"] == straight["history"]["loss"]
    # The run's cost counts the crashed invocation's seconds too (up to its last checkpoint).
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["seconds_since_step"] == 0
    for phase in ("train", "cpu", "wall"):
        assert summary[f"{phase}_seconds"] > round(crashed["elapsed"][phase], 1), phase


def test_a_run_killed_in_its_test_episodes_resumes_without_repeating_its_final_validation(
    tmp_path, data_dir, monkeypatch
):
    from l1flow_rl.workspace.evaluator import PeriodicEvaluator

    run_dir = tmp_path / "run"
    args = ["train", f"data_dir={data_dir}", f"run_dir={run_dir}", *TINY, "train.eval_every=20"]
    real_call = PeriodicEvaluator.__call__

    def killed_in_test(self, actor, step, video_dir=None, split="val"):
        if split == "test":
            raise KeyboardInterrupt("killed during the test episodes")
        return real_call(self, actor, step, video_dir=video_dir, split=split)

    monkeypatch.setattr(PeriodicEvaluator, "__call__", killed_in_test)
    with pytest.raises(KeyboardInterrupt):
        main(args)
    monkeypatch.setattr(PeriodicEvaluator, "__call__", real_call)
    latest = run_dir / "checkpoints" / "latest.pt"
    state = torch.load(latest, weights_only=True)
    assert [(e["step"], e["split"]) for e in state["evals"]] == [(20, "val"), (40, "val")]
    # As a checkpoint written before the totals existed: the summary must say what its seconds cover.
    del state["elapsed"]
    torch.save(state, latest)

    assert main([*args, "resume=true"]) == 0
    evals = json.loads((run_dir / "history.json").read_text())["evals"]
    assert [(e["step"], e["split"]) for e in evals] == [(20, "val"), (40, "val"), (40, "test")]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["seconds_since_step"] == 40 and summary["train_seconds"] == 0.0


def test_eval_command_on_a_checkpoint(tmp_path, full_run):
    out = tmp_path / "eval"
    ckpt = full_run / "checkpoints" / "best.pt"
    assert (
        main(
            [
                "eval",
                f"checkpoint={ckpt}",
                "eval.episodes=2",
                "eval.num_envs=1",
                f"run_dir={out}",
                "task.max_episode_steps=30",
            ]
        )
        == 0
    )
    result = json.loads((out / "eval.json").read_text())
    assert result["episodes"] == 2
    assert set(result) >= {"success_once", "success_at_end"}


def test_the_printed_summary_shows_nested_figures_such_as_the_machine_on_one_line():
    from l1flow_rl.workspace.report import format_summary

    lines = format_summary({"success_once": 0.9, "machine": {"cpu": "X", "torch_threads": 1}}).splitlines()
    assert lines[1:3] == ["success_once  0.900", "machine       cpu X, torch_threads 1"]
