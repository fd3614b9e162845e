"""The simulator benchmark scripts (PushT and robosuite) run end to end on the real simulators in their
quick mode and save what the README's report reads. Speed is never asserted here: a quick run's rates
mean nothing, so only their presence, sign and consistency are."""

from __future__ import annotations

import json

import pytest

from benchmarks.report import speed, success
from l1flow_rl.config import load_task_config

PUSHT_HINT = "needs gym-pusht: pip install 'l1flow-rl[pusht]'"
ROBOSUITE_TASKS = ["robosuite_lift", "robosuite_stack", "robosuite_can", "robosuite_square"]


def _load(path) -> dict:
    figures = json.loads(path.read_text())
    assert figures["quick"] is True  # benchmarks.report skips it: never mistaken for a result
    return figures


def _assert_machine(machine: dict) -> None:
    assert machine["cores"] >= 1 and machine["torch_threads"] == 1 and machine["cpu"]


@pytest.mark.pusht
@pytest.mark.slow  # ~20 s: a benchmark script, run on purpose
def test_pusht_env_quick_mode_rates_every_setting_of_both_observations_against_raw(tmp_path):
    pytest.importorskip("gym_pusht", reason=PUSHT_HINT)
    from benchmarks.speed import bench_pusht_env

    out = tmp_path / "pusht_env.json"
    assert bench_pusht_env.main(["--quick", "--out", str(out)]) == 0
    figures = _load(out)
    assert figures["steps"] == bench_pusht_env.QUICK_STEPS
    # the machine as the report prints it for this file: cores and load average
    assert figures["cpu_count"] >= 1 and len(figures["loadavg_before"]) == len(figures["loadavg_after"]) == 3
    settings = {"raw_gym_pusht", "adapter_1env", "make_env_2envs_serial", "make_env_2envs_parallel"}
    for task in ("pusht", "pusht_image"):
        rates, ratios = figures[task]["steps_per_s"], figures[task]["ratio_to_raw"]
        assert set(rates) == set(ratios) == settings
        assert all(rate > 0 for rate in rates.values())
        raw = rates["raw_gym_pusht"]
        assert ratios == pytest.approx({name: rate / raw for name, rate in rates.items()})
    table = speed.render_sim_throughput(figures)
    assert sum(line.startswith(("| pusht |", "| pusht_image |")) for line in table.splitlines()) == 8


@pytest.mark.pusht
def test_pusht_expert_quick_mode_scores_each_seed_and_sums_up_the_sides(tmp_path):
    pytest.importorskip("gym_pusht", reason=PUSHT_HINT)
    from benchmarks.success import bench_pusht_expert

    out = tmp_path / "pusht_expert.json"
    assert bench_pusht_expert.main(["--quick", "--out", str(out)]) == 0
    figures = _load(out)
    seeds = bench_pusht_expert.QUICK_SEEDS
    assert figures["seeds"] == seeds and figures["workers"] == bench_pusht_expert.QUICK_WORKERS
    assert [r["seed"] for r in figures["per_seed"]] == list(range(seeds))
    assert figures["cpu_count"] >= 1 and len(figures["loadavg_before"]) == 3
    ran = [r for r in figures["per_seed"] if "steps" in r]
    assert ran, f"the planner ran no seed: {figures['per_seed']}"
    for r in ran:
        assert 0 < r["steps"] <= 300 and r["seconds"] > 0 and 0.0 <= r["score"] <= 1.0
        assert r["side"] in ("left", "right", "none")
    assert 0.0 <= figures["success"] <= 1.0 and 0.0 <= figures["mean_score"] <= 1.0
    assert figures["success"] == pytest.approx(sum(r["success"] for r in figures["per_seed"]) / seeds)
    assert figures["steps_mean"] > 0 and figures["seconds_per_episode_mean"] > 0
    assert figures["wall_seconds"] > 0
    assert sum(figures["side_share"].values()) == pytest.approx(1.0)
    assert all(v is None or 0.0 <= v <= 1.0 for v in figures["success_by_side"].values())
    table = success.render_experts(figures)
    assert f"| pusht | {seeds} |" in table and "Share of episodes per side of the block" in table


@pytest.mark.robosuite
@pytest.mark.slow  # ~30 s: a benchmark script, run on purpose
def test_robosuite_experts_quick_mode_runs_every_task_for_its_seeds(tmp_path):
    pytest.importorskip("robosuite", reason="needs robosuite: pip install 'l1flow-rl[robosuite]'")
    from benchmarks.success import bench_robosuite_experts

    out = tmp_path / "robosuite_experts.json"
    assert bench_robosuite_experts.main(["--quick", "--out", str(out)]) == 0
    figures = _load(out)
    _assert_machine(figures["machine_at_start"])
    _assert_machine(figures["machine_at_end"])
    seeds = bench_robosuite_experts.QUICK_SEEDS
    assert [r["task"] for r in figures["rows"]] == ROBOSUITE_TASKS
    for r in figures["rows"]:
        task = load_task_config(r["task"])
        assert r["env_id"] == task.env_id and r["seeds"] == seeds
        assert set(r["failed_seeds"]) <= set(range(seeds))
        assert 0.0 <= r["success_rate"] <= 1.0
        assert r["success_rate"] == (seeds - len(r["failed_seeds"])) / seeds
        assert r["seconds_per_episode"] > 0
        if r["success_rate"] > 0:
            assert 0 < r["steps_per_success_mean"] <= r["steps_per_success_max"] <= task.max_episode_steps
        else:
            assert r["steps_per_success_mean"] is None and r["steps_per_success_max"] is None
    table = success.render_experts(figures)
    assert all(f"| {name} | {seeds} |" in table for name in ROBOSUITE_TASKS)


@pytest.mark.robosuite
@pytest.mark.slow  # ~30 s: a benchmark script, run on purpose
def test_robosuite_throughput_quick_mode_times_each_adapter_against_its_raw_baseline(tmp_path):
    pytest.importorskip("robosuite", reason="needs robosuite: pip install 'l1flow-rl[robosuite]'")
    from benchmarks.speed import bench_robosuite_throughput as bench

    out = tmp_path / "robosuite_throughput_robosuite_lift.json"
    # 2 workers: make_env runs a single env in process, so only 2 or more reach the worker path
    assert bench.main(["--quick", "--workers", "2", "--out", str(out)]) == 0
    figures = _load(out)
    _assert_machine(figures["machine"])
    assert figures["task"] == "robosuite_lift" and figures["env_id"] == "Lift"
    assert figures["timed_steps_per_env"] == bench.QUICK_STEPS and figures["rounds"] == bench.QUICK_ROUNDS
    rows = {r["setting"]: r for r in figures["rows"]}
    assert {name: r["num_envs"] for name, r in rows.items()} == {"cpu_1env": 1, "cpu_2proc": 2}
    adapters = {"cpu_1env": {"unbatched", "make_env"}, "cpu_2proc": {"make_env"}}
    for name, r in rows.items():
        timed = {k.removesuffix("_steps_per_s") for k in r if k.endswith("_steps_per_s")}
        assert timed == {"raw", *adapters[name]}
        assert r["raw_steps_per_s"] > 0
        for side in adapters[name]:
            rate = r[f"{side}_steps_per_s"]
            # both rounded in the file (rates to 0.1, the ratio to 0.001)
            assert rate > 0 and r[f"{side}_over_raw"] == pytest.approx(rate / r["raw_steps_per_s"], rel=0.02)
    table = speed.render_sim_throughput(figures)
    assert all(f"| {name} |" in table for name in rows)
