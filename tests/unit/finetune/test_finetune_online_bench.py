"""The online fine-tuning benchmark's figures: mean and spread over seeds, the control arms, and the
RESULTS.md table drawn from them (synthetic runs with numbers chosen by hand)."""

from __future__ import annotations

import argparse
import json

import pytest

from benchmarks.finetune.bench_finetune_online import (
    last_weights_control,
    last_weights_eval_cmd,
    read_control,
    seeded_control,
)
from benchmarks.lib.stats import runs_aggregate
from benchmarks.report.finetune import render_finetune_online


def _run(curve, test, stopped=False):
    return {
        "stopped_early": stopped,
        "validation": [{"env_steps": x, "phase": "online", "success_once": v} for x, v in curve],
        "test": {"success_once": test, "episodes": 100},
        "env_steps_per_s_actor": 200.0,
        "updates_per_s": 10.0,
    }


def test_aggregate_takes_mean_and_spread_at_the_steps_every_seed_reached():
    runs = {
        0: _run([(0, 0.2), (20_000, 0.4), (40_000, 0.6)], 0.5),
        1: _run([(0, 0.2), (20_000, 0.2)], 0.3, stopped=True),  # stopped before 40k
    }
    agg = runs_aggregate(runs)
    assert agg["seeds"] == [0, 1]
    assert agg["test_mean"] == pytest.approx(0.4) and (agg["test_min"], agg["test_max"]) == (0.3, 0.5)
    assert [c["env_steps"] for c in agg["curve"]] == [0, 20_000]
    assert agg["curve"][1] == {"env_steps": 20_000, "mean": pytest.approx(0.3), "min": 0.2, "max": 0.4}


def test_the_table_shows_controls_and_each_algorithm_with_its_curve(tmp_path):
    (tmp_path / "eval.json").write_text(json.dumps({"success_once": 0.18, "episodes": 100}))
    (tmp_path / "summary.json").write_text(json.dumps({"steps": 2000, "cpu_seconds": 300.0}))
    control = read_control(tmp_path)
    assert control["test"]["success_once"] == 0.18 and control["steps"] == 2000
    # a second seed's control, with the validations its test's selection records
    evaluations = [{"step": 0, "success_once": 0.2}, {"step": 2000, "success_once": 0.3}]
    second = {
        **control,
        "test": {"success_once": 0.3, "episodes": 100, "selection": {"evaluations": evaluations}},
    }
    runs = {0: _run([(0, 0.18), (20_000, 0.3)], 0.32)}
    data = {
        "task": "maniskill_pickcube",
        "checkpoint": "bc.pt",
        "eval_every": 20_000,
        "val_episodes": 50,
        "test_episodes": 100,
        "controls": {
            "bc_start": control,
            "continued_bc": {
                **seeded_control({0: control, 1: second}),
                "updates": 8000,
            },
        },
        "algorithms": {
            "dsrl": {"budget_overrides": ["x=1"], "runs": {"0": runs[0]}, "aggregate": runs_aggregate(runs)}
        },
    }
    table = render_finetune_online(data)
    assert "| bc_start | 1 | 0.18 (100 episodes) |" in table
    # a control run per seed: its mean and spread, its update count, and its validations at exact
    # update counts, saying how many seeds read each (seed 0 records none here)
    assert (
        "| continued_bc, 8,000 updates | 2 | 0.24 (0.18-0.30; 100 episodes) | "
        "0 upd.: 0.20 (1 of 2), 2,000 upd.: 0.30 (1 of 2) |" in table
    )
    assert "| dsrl | 1 | 0.32 (0.32-0.32) | 0k: 0.18, 20k: 0.30 | 200 | 10 |" in table
    assert "dsrl: `x=1`" in table
    # an --override that reached the control too (an EMA) is named in its row
    data["controls"]["continued_bc"]["overrides"] = ["finetune.ema_power=0.75"]
    assert "| continued_bc, 8,000 updates, `finetune.ema_power=0.75` | 2 |" in render_finetune_online(data)
    # data grown by shifted replays: its cost in env steps is named beside the arm
    cost = {"attempts": 200, "successes": 196, "env_steps": 22491}
    data["controls"]["continued_bc"]["seeds"]["1"]["data_cost"] = cost
    data["algorithms"]["dsrl"]["runs"]["0"]["data_cost"] = cost
    table = render_finetune_online(data)
    grown = "; its data: 200 shifted replays, 196 kept, 22,491 env steps"
    assert f"| continued_bc, 8,000 updates, `finetune.ema_power=0.75`{grown} | 2 |" in table
    assert f"| dsrl{grown} | 1 |" in table


def test_a_finished_run_reads_its_closing_validation_at_its_last_env_step(tmp_path):
    from benchmarks.finetune.bench_finetune_online import read_run

    evals = [
        {"split": "val", "phase": "start", "env_steps": 0, "success_once": 0.18},
        {"split": "val", "phase": "online", "env_steps": 20_000, "success_once": 0.2},
        {"split": "val", "success_once": 0.16},  # the harness's closing validation: no phase, no steps
        {"split": "test", "success_once": 0.18},
    ]
    (tmp_path / "history.json").write_text(json.dumps({"evals": evals, "rounds": []}))
    (tmp_path / "summary.json").write_text(json.dumps({"env_steps": 40_000, "online_updates": 8}))
    (tmp_path / "eval.json").write_text(json.dumps({"success_once": 0.18, "episodes": 100}))
    run = read_run(tmp_path)
    assert [(v["env_steps"], v["success_once"]) for v in run["validation"]] == [
        (0, 0.18),
        (20_000, 0.2),
        (40_000, 0.16),
    ]
    assert runs_aggregate({0: run})["curve"][0] == {"env_steps": 0, "mean": 0.18, "min": 0.18, "max": 0.18}


def test_a_run_extended_after_it_finished_reads_each_closing_validation_at_its_env_step(tmp_path):
    """A 60k run resumed to 100k keeps its 60k closing validation among the evaluations; with 200
    offline updates first, the harness's step is offline updates + env steps."""
    from benchmarks.finetune.bench_finetune_online import at_asked_length, read_run

    evals = [
        {"step": 0, "split": "val", "phase": "start", "env_steps": 0, "success_once": 0.44},
        {"step": 60_200, "split": "val", "phase": None, "env_steps": None, "success_once": 0.52},
        {"step": 80_200, "split": "val", "phase": "online", "env_steps": 80_000, "success_once": 0.5},
        {"step": 100_200, "split": "val", "phase": None, "env_steps": None, "success_once": 0.6},
        {"step": 100_200, "split": "test", "success_once": 0.58},
    ]
    (tmp_path / "history.json").write_text(json.dumps({"evals": evals, "rounds": []}))
    summary = {"env_steps": 100_000, "offline_updates": 200, "online_updates": 8}
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    (tmp_path / "eval.json").write_text(json.dumps({"success_once": 0.58, "episodes": 100}))
    steps = [(v["env_steps"], v["success_once"]) for v in read_run(tmp_path)["validation"]]
    assert steps == [(0, 0.44), (60_000, 0.52), (80_000, 0.5), (100_000, 0.6)]
    # the bench extends a finished run shorter than asked, and a control with fewer updates
    ask = argparse.Namespace(steps=100_000, continued_bc_updates=8000)
    assert at_asked_length(tmp_path, "filtered_bc", ask)
    assert not at_asked_length(tmp_path, "filtered_bc", argparse.Namespace(steps=150_000))
    assert not at_asked_length(tmp_path, "continued_bc", ask)  # 200 offline updates of 8000
    (tmp_path / "eval.json").unlink()
    assert not at_asked_length(tmp_path, "filtered_bc", ask)  # no report: interrupted, resumed


def test_the_continued_bc_last_weights_control_is_an_eval_of_latest_on_the_test_seeds(tmp_path):
    args = argparse.Namespace(task="robosuite_can", test_episodes=100)
    control_dir = tmp_path / "robosuite_can_continued_bc_seed0"
    cmd = last_weights_eval_cmd(args, control_dir, tmp_path / "out")
    assert cmd[3:] == [
        "eval",
        f"checkpoint={control_dir / 'checkpoints' / 'latest.pt'}",
        "task=robosuite_can",
        f"run_dir={tmp_path / 'out'}",
        "eval.episodes=100",
    ]
    # an ``l1flow-rl eval`` run has eval.json and no summary.json: read with no step or CPU count
    (tmp_path / "eval.json").write_text(json.dumps({"success_once": 0.16, "episodes": 100}))
    control = read_control(tmp_path)
    assert control["test"]["success_once"] == 0.16 and control["steps"] is None


def test_an_override_replaces_the_budgets_value_of_the_same_key():
    from benchmarks.finetune.bench_finetune_online import CPU_BUDGET, budget

    assert "online.updates_per_step=0.05" in CPU_BUDGET["qc"]
    merged = budget("qc", ["online.updates_per_step=0.1", "finetune.qc.freeze_flow=true"])
    expected = ["finetune.qc.num_samples=8", "online.updates_per_step=0.1", "finetune.qc.freeze_flow=true"]
    assert merged == expected
    assert budget("filtered_bc", []) == []


def test_last_weights_are_collected_per_seed_and_an_untested_seed_is_left_out(tmp_path):
    # an online run's last weights beside its validated choice (PickCube mixed-50 seeds 0 and 1 kept
    # their start by validation, 0.33 / 0.32; their last weights tested 0.36 / 0.39)
    import argparse

    finished = {}
    for seed, rate in ((0, 0.36), (1, 0.39), (2, None)):
        run = tmp_path / f"task_filtered_bc_seed{seed}"
        run.mkdir()
        finished[seed] = run
        if rate is not None:
            last = tmp_path / f"{run.name}_last"
            last.mkdir()
            (last / "eval.json").write_text(json.dumps({"success_once": rate, "episodes": 100}))
    args = argparse.Namespace(collect_only=True)  # reads only: seed 2's test is not run
    control = last_weights_control(finished, args)
    assert sorted(control["seeds"]) == ["0", "1"]
    assert control["test"]["success_once"] == pytest.approx(0.375)
    assert (control["test"]["min"], control["test"]["max"], control["test"]["episodes"]) == (0.36, 0.39, 100)
    assert last_weights_control({2: finished[2]}, args) is None


def test_a_restored_run_without_checkpoints_is_named_and_its_last_weights_are_not_tested(tmp_path, capsys):
    # a run copied with its records but not its checkpoints: no eval is launched
    import argparse

    run = tmp_path / "task_continued_bc_seed0"
    run.mkdir()
    (run / "eval.json").write_text(json.dumps({"success_once": 0.34, "episodes": 100}))
    args = argparse.Namespace(collect_only=False, task="robosuite_can", test_episodes=100)
    assert last_weights_control({0: run}, args) is None
    assert f"{run} has no checkpoints/latest.pt" in capsys.readouterr().out
    assert not (tmp_path / "task_continued_bc_seed0_last.log").exists()  # no eval was started


def test_a_run_on_shifted_replays_reports_what_making_its_data_cost(tmp_path):
    import h5py

    from benchmarks.finetune.bench_finetune_online import data_cost

    grown = tmp_path / "can.n30.mixed.shift200.hdf5"
    with h5py.File(grown, "w") as f:
        f.create_group("data").attrs["shifted_replays"] = json.dumps({"attempts": 200, "env_steps": 22491})
    plain = tmp_path / "can.n30.hdf5"
    with h5py.File(plain, "w") as f:
        f.create_group("data")
    assert data_cost(str(grown)) == {"attempts": 200, "env_steps": 22491}
    assert data_cost(str(plain)) is None  # demonstrations only: nothing beyond the start's data
    assert data_cost(None) is None and data_cost(str(tmp_path / "missing.hdf5")) is None
    assert data_cost(str(tmp_path / "episodes.zarr")) is None


def test_the_td_only_arm_is_the_algorithms_preset_and_budget_on_the_demonstrations_alone(tmp_path):
    """``--offline-only-updates``: the arm that separates "online data" from "TD" composes into the
    algorithm's own preset and CPU budget with no env step, is extended like the continued-BC control,
    and shows in the table as a seeded control at its update counts."""
    from benchmarks.finetune.bench_finetune_online import at_asked_length, offline_only_cmd
    from l1flow_rl.commands.cli import compose_config

    args = argparse.Namespace(
        checkpoint="bc.pt",
        task="robosuite_can",
        offline_only_updates=6500,
        test_episodes=100,
        val_episodes=50,
        override=["finetune.qc.freeze_flow=true", "online.updates_per_step=0.1"],
    )
    cmd = offline_only_cmd("qc", 0, args, tmp_path / "run")
    assert cmd[3:5] == ["finetune", "finetune=qc"]
    cfg = compose_config(cmd[5:], command="finetune")
    assert cfg.finetune.algorithm == "qc" and cfg.online.steps == 0
    assert (cfg.offline.steps, cfg.offline.eval_every) == (6500, 1625)  # the preset's 2,000 replaced
    assert cfg.finetune.qc.num_samples == 8 and cfg.finetune.qc.freeze_flow  # the budget, then --override
    # the online runs' offline phase, given as an override, is part of the arm's N, not a second value
    args.override = [*args.override, "offline.steps=3000", "online.steps=50000"]
    cfg = compose_config(offline_only_cmd("qc", 0, args, tmp_path / "run")[5:], command="finetune")
    assert (cfg.offline.steps, cfg.online.steps, cfg.online.updates_per_step) == (6500, 0, 0.1)
    # flow-Q's preset trains the critics alone offline (as would an --override): its TD-only arm's
    # actor learns, or the arm would test the start itself
    args.override = ["offline.critic_only=true"]
    for algorithm in ("flowq", "qc"):
        cfg = compose_config(offline_only_cmd(algorithm, 0, args, tmp_path / "run")[5:], command="finetune")
        assert cfg.offline.critic_only is False and cfg.offline.steps == 6500
    assert compose_config(["finetune=flowq"], command="finetune").offline.critic_only is True
    # asked at 6,500 updates: a finished run of 1,625 is extended, one of 6,500 is read
    run = tmp_path / "run"
    run.mkdir()
    (run / "eval.json").write_text(json.dumps({"success_once": 0.3, "episodes": 100}))
    (run / "summary.json").write_text(json.dumps({"offline_updates": 1625, "env_steps": 0}))
    assert not at_asked_length(run, "qc_offline", args)
    (run / "summary.json").write_text(json.dumps({"offline_updates": 6500, "env_steps": 0}))
    assert at_asked_length(run, "qc_offline", args)
    evaluations = [{"step": 0, "success_once": 0.38}, {"step": 6500, "success_once": 0.3}]
    test = {"success_once": 0.3, "episodes": 100, "selection": {"evaluations": evaluations}}
    control = {**seeded_control({0: {**read_control(run), "test": test}}), "updates": 6500}
    control["overrides"] = ["finetune.qc.freeze_flow=true"]
    data = {
        "task": "robosuite_can",
        "checkpoint": "bc.pt",
        "eval_every": 25_000,
        "val_episodes": 50,
        "test_episodes": 100,
        "controls": {"qc_offline": control},
        "algorithms": {},
    }
    assert (
        "| qc_offline, 6,500 updates, `finetune.qc.freeze_flow=true` | 1 | 0.30 (0.30-0.30; 100 episodes) | "
        "0 upd.: 0.38, 6,500 upd.: 0.30 |" in render_finetune_online(data)
    )
