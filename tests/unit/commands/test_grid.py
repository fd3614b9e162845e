"""A benchmark grid is a hydra multirun (``configs/grid/``, ``+grid=NAME``) that any launcher runs: a
local process pool (joblib) runs one end to end, a grid killed mid-way and launched again skips its
finished jobs and resumes the others to the figures of an uninterrupted grid, and the re-scoring of
its networks is an ``eval -m`` over its checkpoints; the results script reads the grid's folder."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

TESTS = Path(__file__).parents[2]
#: the point-mass double's two-job grid (tests/doubles/configs/grid/point_mass.yaml), two at a time
GRID = ["--config-dir", str(TESTS / "doubles" / "configs"), "+grid=point_mass"]
POOL = ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"]
SEEDS = ("seed0", "seed1")


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(TESTS), "OMP_NUM_THREADS": "1"}


def _launch(cwd: Path, *args: str) -> subprocess.Popen:
    """``l1flow-rl ARGS`` (with the double registered) in a session of its own, so that killing it
    kills its pool's workers too."""
    log = (cwd / "launch.log").open("a")
    return subprocess.Popen(
        [sys.executable, "-m", "doubles.cli", *args],
        cwd=cwd,
        env=_env(),
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


def _wait(proc: subprocess.Popen, cwd: Path, timeout: float = 300) -> str:
    code = proc.wait(timeout=timeout)
    text = (cwd / "launch.log").read_text()
    assert code == 0, text[-4000:]
    return text


def _runs(grid: Path) -> dict[str, Path]:
    return {seed: grid / "point_mass_reach" / "l1flow" / seed for seed in SEEDS}


def _figures(run_dir: Path) -> dict:
    """What a run measured: its test figures and its validation curve (timings and provenance left out)."""
    result = json.loads((run_dir / "eval.json").read_text())
    history = json.loads((run_dir / "history.json").read_text())
    test = {k: result[k] for k in ("success_once", "success_at_end", "return", "episode_length", "ci95")}
    curve = [(e["step"], e["split"], e["success_once"], e["return"]) for e in history["evals"]]
    return {"test": test, "curve": curve, "selection": result["selection"]["step"]}


@pytest.mark.slow  # ~65 s on 2 busy cores: three launches of a process pool, two of eval
def test_a_grid_killed_midway_resumes_to_the_figures_of_an_uninterrupted_one(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")  # the launchers extra
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    whole.mkdir(), killed.mkdir()
    # the uninterrupted grid beside the one that will be killed
    reference = _launch(whole, "train", "-m", *GRID, *POOL)
    first = _launch(killed, "train", "-m", *GRID, *POOL)
    runs = _runs(killed / "runs" / "grid" / "point_mass")
    interrupted: list[str] = []
    deadline = time.monotonic() + 240
    while not interrupted and first.poll() is None and time.monotonic() < deadline:
        # a run with a checkpoint that has not finished: kill the whole grid there (no signal to
        # handle, as a machine lost)
        interrupted = [
            seed
            for seed, run in runs.items()
            if (run / "checkpoints" / "latest.pt").is_file() and not (run / "summary.json").is_file()
        ]
        time.sleep(0.05)
    assert interrupted, "the grid finished before it could be killed mid-way"
    os.killpg(first.pid, signal.SIGKILL)
    first.wait(timeout=60)
    state = {
        seed: "finished"
        if (run / "summary.json").is_file()
        else "checkpointed"
        if (run / "checkpoints" / "latest.pt").is_file()
        else "started"
        for seed, run in runs.items()
    }

    again = _wait(_launch(killed, "train", "-m", *GRID, *POOL), killed)
    _wait(reference, whole)
    for seed, run in runs.items():
        record = json.loads((run / "eval.json").read_text())["provenance"]
        assert record["launcher"] == "joblib" and record["commits"]  # what ran it, at which commit
        if state[seed] == "finished":  # read back, not trained again
            assert f"{run.relative_to(killed)} holds this run, finished" in again
        elif state[seed] == "checkpointed":  # continued from its checkpoint, not started again
            assert record["resumed_at"] and record["resumed_at"][0] > 0, again[-3000:]
        assert _figures(run) == _figures(_runs(whole / "runs" / "grid" / "point_mass")[seed]), state

    # the grid's networks re-scored at their last weights: an eval -m over its checkpoints, each into
    # <run>/rescore_last_weights/; a relaunch skips them
    rescore = ["eval", "-m", *GRID, "+rescore=last_weights"]
    _wait(_launch(killed, *rescore), killed)
    for run in runs.values():
        record = json.loads((run / "rescore_last_weights" / "eval.json").read_text())
        assert record["checkpoint"].endswith(f"{run.name}/checkpoints/latest.pt")
    assert _wait(_launch(killed, *rescore), killed).count("holds this evaluation, finished") == len(SEEDS)

    # the results script reads the grid's folder: both seeds, their re-scoring, the runs' provenance
    from benchmarks.success import bench_success

    grid = killed / "runs" / "grid" / "point_mass"
    assert bench_success.main([str(grid), "--quick", "--out-dir", str(tmp_path)]) == 0
    saved = json.loads((tmp_path / "success_point_mass_reach_quick.json").read_text())
    block = saved["tasks"]["point_mass_reach"]
    assert set(block) == {"l1flow", "l1flow_last_weights"} and block["l1flow"]["success_once"]["n"] == 2
    assert [r["seed"] for r in block["l1flow"]["per_seed"]] == [0, 1]
    runs_record = saved["provenance"]["runs"]
    assert runs_record["launchers"] == ["basic", "joblib"] and runs_record["commits"]  # eval's, train's
    assert runs_record["swept"] == {"seed": [0, 1]} and runs_record["config"]["train"]["steps"] == 60
    assert saved["args"]["steps"] == 60 and saved["args"]["seeds"] == [0, 1]


def test_a_grid_is_validated_whole_before_any_job_starts(tmp_path, capsys, monkeypatch):
    from doubles.point_mass import TASK_OVERRIDES  # noqa: F401  registers the double here

    from l1flow_rl.commands.cli import main

    monkeypatch.chdir(tmp_path)
    # the grid's sweep (hydra.sweeper.params) is expanded with the command line's: a bad value in one
    # job refuses the whole grid, naming it, before a folder is made
    assert main(["train", "-m", *GRID, "seed=0,-1"]) == 2
    assert "seed=-1" in capsys.readouterr().err and not (tmp_path / "runs").exists()
    # a re-scoring needs the grid's checkpoints: missing, it is refused naming the first
    assert main(["eval", "-m", *GRID, "+rescore=last_weights"]) == 2
    assert (
        "runs/grid/point_mass/point_mass_reach/l1flow/seed0/checkpoints/latest.pt" in capsys.readouterr().err
    )


@pytest.mark.parametrize(
    "grid", ["success_maniskill", "success_pusht", "success_robosuite", "success_square"]
)
def test_every_success_grid_composes_its_sweep_into_its_own_folder(grid):
    from hydra.types import RunMode

    from l1flow_rl.commands.cli import _compose, _create_hydra, _sweep_jobs

    hydra = _create_hydra("train")
    jobs = _sweep_jobs(hydra, [f"+grid={grid}"])
    full = _compose(hydra, jobs[0], RunMode.MULTIRUN)
    assert full.hydra.sweep.dir == f"runs/grid/{grid}" and full.resume == "auto"
    assert (full.train.steps, full.eval.episodes) == (12000, 100)
    policies = {o.split("=")[1] for job in jobs for o in job if o.startswith("policy=")}
    assert policies == {"l1flow", "flow", "ddpm", "regression"}
    assert {o for job in jobs for o in job if o.startswith("seed=")} == {"seed=0", "seed=1", "seed=2"}


def test_the_peginsertion_grid_runs_every_method_on_the_mlp_at_maniskills_budget():
    from hydra.types import RunMode

    from l1flow_rl.commands.cli import _compose, _create_hydra, _sweep_jobs

    hydra = _create_hydra("train")
    jobs = _sweep_jobs(hydra, ["+grid=success_peginsertion"])
    assert len(jobs) == 12  # four methods x three seeds
    full = _compose(hydra, jobs[0], RunMode.MULTIRUN)
    assert full.hydra.sweep.dir == "runs/grid/success_peginsertion" and full.resume == "auto"
    assert (full.task.name, full.network.name, full.demos.num) == ("maniskill_peginsertion", "mlp", 100)
    assert (full.train.steps, full.train.eval_every, full.eval.episodes) == (100000, 10000, 100)


@pytest.mark.parametrize(
    ("grid", "task", "demos", "teachers"),
    [
        ("distillation_can", "robosuite_can", ("expert", 100), {"edm", "ddpm"}),
        ("distillation_square", "robosuite_square", ("expert", 200), {"edm", "ddpm"}),
        ("distillation_square_mh", "robosuite_square", ("mixed", 200), {"edm", "ddpm", "l1flow"}),
        ("distillation_pusht", "pusht", ("expert", 200), {"edm", "ddpm"}),
    ],
)
def test_a_distillation_grid_trains_its_teachers_and_each_distill_option_its_students(
    grid, task, demos, teachers
):
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from l1flow_rl.commands.cli import _compose, _create_hydra, _sweep_jobs

    hydra = _create_hydra("train")
    jobs = _sweep_jobs(hydra, [f"+grid={grid}"])
    full = _compose(hydra, jobs[0], RunMode.MULTIRUN)
    assert full.hydra.sweep.dir == f"runs/grid/{grid}" and full.network.name == "mlp"
    assert (full.task.name, full.demos.quality, full.demos.num) == (task, *demos)
    assert {o.split("=")[1] for job in jobs for o in job if o.startswith("policy=")} == teachers
    # each student from its own seed's teacher in the grid's folder, on its paper's share of the budget
    students = {
        "cp": ({"consistency"}, "edm", 5400, "edm_consistency", 1000.0),
        "onedp_edm": ({"onedp_d", "onedp_s"}, "edm", 240, "onedp_edm", 1000.0),
        "onedp_ddpm": ({"onedp_d_ddpm", "onedp_s_ddpm"}, "ddpm", 240, "onedp_ddpm", 1.0),
    }
    try:
        for distill, (names, teacher, steps, sampler, scale) in students.items():
            jobs = _sweep_jobs(hydra, [f"+grid={grid}", f"+distill={distill}"])
            assert len(jobs) == 3 * len(names)
            seen = set()
            for job in jobs:
                cfg = _compose(hydra, job, RunMode.MULTIRUN)
                HydraConfig.instance().set_config(cfg)  # as in the job: ${hydra:sweep.dir} resolves
                seed = cfg.seed
                want = f"runs/grid/{grid}/{task}/{teacher}/seed{seed}/checkpoints/best.pt"
                assert cfg.teacher == want and cfg.train.steps == steps
                assert (cfg.policy.sampler, cfg.network.timestep_scale) == (sampler, scale)
                seen.add(cfg.policy.name)
            assert seen == names
    finally:
        HydraConfig.instance().cfg = None  # the singleton as the other tests expect it
