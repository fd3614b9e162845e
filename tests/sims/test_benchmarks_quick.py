"""The benchmark scripts run end to end in their quick mode and save what the README's report reads.
Speed is never asserted here (figures come from the scripts' own runs); structure and NFE are."""

import json

import pytest

from benchmarks.speed import bench_latency


def test_latency_quick_mode_saves_every_method_with_its_nfe(tmp_path):
    out = tmp_path / "latency.json"
    assert bench_latency.main(["--quick", "--out", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert figures["quick"] is True and figures["machine"]["cores"] >= 1
    expected_nfe = {
        "l1flow_2nfe": 2,
        "euler1": 1,
        "euler2": 2,
        "euler5": 5,
        "euler10": 10,
        "vflow_euler10": 10,
        "ddim16": 16,
        "ddpm100": 100,
        "regression": 1,
        "edm_heun18": 35,  # Heun: 2N - 1 network calls for N levels
        "edm_heun10": 19,
        "cp1": 1,
        "cp3": 3,
        "onedp1": 1,
        "floor_2_unet": 2,
        "diffusers_ddpm100": 100,
        "diffusers_ddim16": 16,
    }
    assert figures["nfe"] == expected_nfe
    block = figures["inference"]["batch1"]
    assert set(block["ms"]) == set(expected_nfe)
    assert block["slowdown_vs_l1flow"]["l1flow_2nfe"] == 1.0
    assert all(v["wall_ms"] > 0 and v["cpu_ms"] >= 0 for v in block["ms"].values())
    assert block["l1flow_over_floor"] > 0
    assert set(figures["train_step_ms"]["ms"]) == {
        "l1flow_2nfe",
        "vflow_euler10",
        "ddpm100",
        "regression",
        "edm_heun18",
        "consistency",
        "onedp_d",
        "onedp_s",
    }


def test_multimodal_quick_mode_reports_every_family_and_evaluation(tmp_path):
    from benchmarks.success import bench_multimodal

    out = tmp_path / "multimodal.json"
    assert bench_multimodal.main(["--quick", "--out", str(out), "--methods", "l1flow", "regression"]) == 0
    figures = json.loads(out.read_text())
    assert {f: b["num_modes"] for f, b in figures["families"].items()} == {
        "opposite_sines": 2,
        "nested_amplitudes": 4,
        "phase_shifts": 8,
    }
    for block in figures["families"].values():
        evaluations = block["methods"]
        assert set(evaluations) == {
            "l1flow",
            "l1flow_tfirst0.3",
            "l1flow_tfirst0.7",
            "l1flow_euler10",
            "regression",
        }
        for r in evaluations.values():
            assert len(r["shares"]) == block["num_modes"]
            assert sum(r["shares"]) + r["share_neither"] == pytest.approx(1.0)


def test_latency_quick_mode_times_the_image_network_under_every_sampler(tmp_path):
    out = tmp_path / "latency_image.json"
    assert bench_latency.main(["--quick", "--network", "image", "--no-peers", "--out", str(out)]) == 0
    figures = json.loads(out.read_text())
    net = figures["network"]
    assert net["kind"] == "image" and net["task"] == "maniskill_pushcube_rgb" and net["down_dims"] == [16, 32]
    # the ResNet-18 trunk alone has ~11M parameters: the encoder is in the timed network
    assert net["parameters"] > 10_000_000
    block = figures["inference"]["batch1"]
    assert set(block["ms"]) == set(bench_latency.SAMPLERS) | {"floor_2_unet"}
    assert all(v["wall_ms"] > 0 for v in block["ms"].values())
    assert "train_step_ms" not in figures  # bench_image_train times the image network's training


def test_ablations_table_pairs_each_variant_with_the_default_on_the_same_seed():
    from benchmarks.report import success as report

    def block(kind, rates):
        per_seed = [{"success_once": r, "episodes": 50} for r in rates]
        return {"kind": kind, "success_once": {"mean": sum(rates) / len(rates)}, "per_seed": per_seed}

    d = {
        "args": {
            "task": "maniskill_pushcube",
            "demos": 20,
            "steps": 2500,
            "eval_episodes": 50,
            "seeds": [0, 1],
        },
        "variants": {"default": block("loss", [0.5, 0.7]), "euler1": block("sampler", [0.56, 0.76])},
    }
    text = report.render_ablations(d)
    # paired: ((0.56 - 0.5) + (0.76 - 0.7)) / 2 = +0.06; pooled Wilson of 66 in 100: [0.563, 0.745]
    assert "| euler1 | sampler | 0.56 / 0.76 | 0.66 | [0.56, 0.75] | +0.060 |" in text
    # pooled Wilson over 100 episodes with 60 successes: [0.502, 0.691]
    assert "| default | loss | 0.50 / 0.70 | 0.6 | [0.50, 0.69] | – |" in text
    assert "seeds 0, 1" in text


def test_success_table_budget_leaves_out_runs_timed_only_from_a_resume():
    from benchmarks.report import success as report

    seed = {"success_once": 0.5, "episodes": 50, "steps": 2500, "curve": [[2500, 0.5]]}
    tree = {"cpu_seconds_scope": "process tree"}
    per_seed = [
        {**seed, **tree, "cpu_seconds": 1000.0, "seconds_since_step": 0},
        {**seed, **tree, "cpu_seconds": 1400.0},  # a summary written before the field existed
        {**seed, **tree, "cpu_seconds": 140.0, "seconds_since_step": 2500},  # only the resumed test
    ]
    stats = {"mean": 0.5, "std": 0.0, "min": 0.5, "max": 0.5, "n": 3}
    d = {"tasks": {"pusht": {"flow": {"success_once": stats, "per_seed": per_seed}}}}
    text = report.render_success([("success_pusht.json", d)])
    row = next(
        line for line in text.splitlines() if line.startswith("| `success_pusht.json` | pusht | flow |")
    )
    assert row.rstrip(" |").endswith("| 1,200"), row  # (1000 + 1400) / 2, the partial run left out
    assert "cover only the last invocation): pusht flow: 1 run(s)." in text
    assert "†" not in text

    # Runs recorded before the CPU seconds covered simulator workers: the figure is marked as a floor.
    per_seed[0].pop("cpu_seconds_scope")
    text = report.render_success([("success_pusht.json", d)])
    row = next(
        line for line in text.splitlines() if line.startswith("| `success_pusht.json` | pusht | flow |")
    )
    assert row.rstrip(" |").endswith("| 1,200 †"), row
    assert "†: the runs' own processes only" in text


def test_claims_table_applies_its_rules_to_the_saved_figures_including_contradictions(tmp_path):
    from benchmarks.report.claims import claims_table

    assert claims_table(tmp_path) is None  # nothing measured, no table

    def method(rates, steps):
        per_seed = [{"success_once": r, "episodes": 50} for r in rates]
        mean = sum(rates) / len(rates)
        stats = {"mean": mean, "n": len(rates)}
        return {
            "metric": "success_once",
            "success_once": stats,
            "per_seed": per_seed,
            "steps_to_90pct_of_best": steps,
        }

    tasks = {
        # L1 Flow clearly below DDPM-100 (pooled 30/100 against 90/100), yet it converges in fewer steps
        "a": {"l1flow": method([0.3, 0.3], [500, 500]), "ddpm": method([0.9, 0.9], [1500, 2500])},
        # within each other's intervals, but flow reaches 90 % of its best sooner
        "b": {"l1flow": method([0.8, 0.84], [1000, 1000]), "flow": method([0.82, 0.84], [500, 500])},
        # from curves: flow's second seed first nears its best at its last validation (still rising),
        # so its 1.5x is a lower bound; DDPM-100's 0.75x is a measurement
        "c": {
            "l1flow": {**method([0.8], []), "curves": [[[500, 0.1], [1000, 0.8], [1500, 0.8]]]},
            "flow": {
                **method([0.3], []),
                "curves": [[[500, 0.0], [1000, 0.3]], [[500, 0.1], [1000, 0.1], [1500, 0.4]]],
            },
            "ddpm": {**method([0.8], []), "curves": [[[500, 0.0], [750, 0.8], [1500, 0.8]]]},
        },
    }
    (tmp_path / "success_x.json").write_text(json.dumps({"quick": False, "tasks": tasks}))
    (tmp_path / "success_y_quick.json").write_text(json.dumps({"quick": True, "tasks": tasks}))
    # a sweep that changed the network: as saved before the network group, a network override, another network
    ablation = {"quick": False, "args": {"extra": ["policy.timestep_scale=1000"]}, "tasks": tasks}
    (tmp_path / "success_z_ablation.json").write_text(json.dumps(ablation))
    for name, override in (("network", "network.timestep_scale=1000"), ("mlp", "network=mlp")):
        changed = {"quick": False, "args": {"extra": [override]}, "tasks": tasks}
        (tmp_path / f"success_z_{name}.json").write_text(json.dumps(changed))
    latency = {
        "machine": {"device": "cpu"},
        "inference": {
            "batch1": {
                "ms": {"l1flow_2nfe": {"wall_ms": 2.0}},
                "slowdown_vs_l1flow": {"ddim16": 7.9, "ddpm100": 48.0},
            }
        },
    }
    (tmp_path / "latency.json").write_text(json.dumps(latency))
    text = claims_table(tmp_path)
    rows = {line.split(" | ")[1]: line for line in text.splitlines() if line.startswith("| ") and "(" in line}
    assert text.count("`success_x.json`") == 6 and "success_y_quick" not in text  # quick files never count
    assert "success_z_" not in text  # nor a sweep that changed the policy (its network included)
    a, b, _ = (line for line in text.splitlines() if "2 NFE match" in line)
    assert a.endswith("| below DDPM-100 |") and b.endswith("| holds |")
    conv_a, conv_b, conv_c = (line for line in text.splitlines() if "converges faster" in line)
    # flow: (1000 + 1500) / 2 / 1000, a bound since one seed was still rising; DDPM-100: 750 / 1000
    expected = "flow (Euler 10) ≥ 1.2× the steps (still rising); DDPM-100 0.75× the steps"
    assert f"| 1,000 steps to 90 % of best | {expected} | not fewer than DDPM-100 |" in conv_c
    assert "DDPM-100 4× the steps | fewer steps than all |" in conv_a  # (1500 + 2500) / 2 / 500
    assert "flow (Euler 10) 0.5× the steps | not fewer than flow (Euler 10) |" in conv_b
    speed = rows["state UNet, batch1, cpu (`latency.json`)"]
    assert "DDIM-16 7.9× slower; DDPM-100 48× slower | outside 10-70× for DDIM-16 |" in speed


def test_success_overview_puts_every_compared_task_in_one_table_and_figure(tmp_path):
    from benchmarks.report.success_overview import overview_figure, overview_table

    assert overview_table(tmp_path) is None and not overview_figure(tmp_path, tmp_path / "o.png")

    def method(rates, metric="success_once", score=None):
        per_seed = [{"success_once": r, "episodes": 50} for r in rates]
        block = {
            "metric": metric,
            "success_once": {"mean": sum(rates) / len(rates), "n": len(rates)},
            "per_seed": per_seed,
            "curves": [[[500, r / 2], [1000, r]] for r in rates],
        }
        if score is not None:
            block[metric] = {"mean": score, "n": len(rates)}
        return block

    def save(name, tasks, quick=False, demos=100):
        args = {"demos": demos, "steps": 2500}
        (tmp_path / name).write_text(json.dumps({"quick": quick, "args": args, "tasks": tasks}))

    save("success_a.json", {"cube": {"l1flow": method([0.6, 0.6]), "ddpm": method([0.8, 0.8])}})
    save(
        "success_b.json", {"t": {"l1flow": method([0.7], "score", 0.95), "flow": method([0.2], "score", 0.9)}}
    )
    save("success_c.json", {"lone": {"l1flow": method([0.9])}})  # nothing to compare with
    save("success_a_ddpm.json", {"cube": {"ddpm": method([0.0, 0.0]), "ddpm_ddim16": method([0.0, 0.0])}})
    save("success_d_quick.json", {"q": {"l1flow": method([1.0]), "flow": method([1.0])}}, quick=True)
    e = {"quick": False, "args": {"demos": 9, "steps": 5, "extra": ["network.timestep_scale=1000"]}}
    (tmp_path / "success_e.json").write_text(
        json.dumps({**e, "tasks": {"z": {"l1flow": method([0.5]), "flow": method([0.5])}}})
    )
    text = overview_table(tmp_path)
    rows = [line for line in text.splitlines() if line.startswith("| ") and "`" in line]
    # lone and quick files left out; a DDPM-only file (its seeds finished later) gets its own row
    assert [r.split(" | ")[0] for r in rows] == ["| cube", "| cube", "| t", "| z"]
    assert (
        "9 demos, 5 steps, 1 seed, `network.timestep_scale=1000` (`success_e.json`)" in rows[3]
    )  # overrides shown
    zeros = "| – | – | 0.000 [0.00, 0.04] | 0.000 [0.00, 0.04] | – |"  # no bold: nothing to single out
    assert f"2 seeds (`success_a_ddpm.json`) {zeros}" in rows[1]
    # pooled Wilson: 60/100 -> [0.50, 0.69], 80/100 -> [0.71, 0.87]; the higher mean in bold
    assert "| 0.600 [0.50, 0.69] | – | **0.800 [0.71, 0.87]** | – | – |" in rows[0]
    assert "100 demos, 2,500 steps, 2 seeds (`success_a.json`)" in rows[0]
    assert "| **0.950 (score; success 0.70)** | 0.900 (score; success 0.20) |" in rows[2]
    assert overview_figure(tmp_path, tmp_path / "o.png") and (tmp_path / "o.png").stat().st_size > 0


@pytest.mark.slow  # ~25 s: a benchmark script, run on purpose
def test_train_throughput_quick_mode_times_every_arm_and_cuda_latency_refuses_without_cuda(tmp_path, capsys):
    import torch

    from benchmarks.speed import bench_latency_cuda, bench_train_throughput

    out = tmp_path / "train_throughput.json"
    argv = ["--quick", "--device", "cpu", "--compile", "off", "--out", str(out)]
    assert bench_train_throughput.main(argv) == 0
    figures = json.loads(out.read_text())
    assert figures["quick"] is True and figures["machine"]["device"] == "cpu"
    assert set(figures["networks"]) == {"state", "image"}
    assert figures["networks"]["image"]["encoder"] == "resnet18_gn"
    for block in figures["networks"].values():
        assert set(block["settings"]) == {"fp32_eager", "bf16_eager"}
        for r in block["settings"].values():
            assert set(r["step_ms"]) == {"trainer", "trainer_resident", "model"}
            assert all(v["wall_ms"] > 0 for v in r["step_ms"].values())
            ms = {arm: v["wall_ms"] for arm, v in r["step_ms"].items()}
            assert r["trainer_over_model"] == pytest.approx(ms["model"] / ms["trainer"], rel=1e-2)
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit) as exit_info:
            bench_latency_cuda.main(["--quick", "--out", str(tmp_path / "latency_cuda.json")])
        assert exit_info.value.code == 2
        assert "needs a CUDA GPU" in capsys.readouterr().err
        assert not (tmp_path / "latency_cuda.json").exists()


def test_sampler_quick_mode_measures_sampling_against_the_training_step(tmp_path):
    from benchmarks.speed import bench_sampler

    out = tmp_path / "sampler.json"
    assert bench_sampler.main(["--quick", "--out", str(out), "--device", "cpu"]) == 0
    figures = json.loads(out.read_text())
    assert figures["quick"] is True and figures["machine"]["cores"] >= 1
    assert (figures["batch_size"], figures["obs_horizon"], figures["pred_horizon"]) == (256, 2, 16)
    rates = [
        "state_chunks_per_s",
        "rgb128_chunks_per_s",
        "train_chunks_per_s",
        "train_from_buffer_chunks_per_s",
    ]
    assert all(figures[k] > 0 for k in rates)
    # the ratios the README reads are the rates' own quotients, to their rounding
    ratio = figures["state_chunks_per_s"] / figures["train_chunks_per_s"]
    assert figures["state_sampler_over_train"] == pytest.approx(ratio, rel=0.01, abs=0.01)


@pytest.mark.slow  # ~70 s: worker processes start for each of its settings
@pytest.mark.maniskill
def test_env_throughput_quick_mode_times_adapters_against_raw_maniskill(tmp_path):
    pytest.importorskip("mani_skill", reason="needs ManiSkill: pip install 'l1flow-rl[maniskill]'")
    from benchmarks.speed import bench_env_throughput

    out = tmp_path / "env.json"
    assert bench_env_throughput.main(["--quick", "--out", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert figures["quick"] is True and figures["task"] == "maniskill_pushcube"
    assert (figures["timed_steps_per_env"], figures["rounds"]) == (4, 2)
    settings = {r["setting"]: r for r in figures["rows"]}
    assert {"cpu_1env", "cpu_2proc"} <= set(settings)
    assert set(settings["cpu_2proc"]["adapters"]) == {"async", "parallel"}
    assert set(settings["cpu_1env"]["adapters"]) == {"in_process", "l1flow_policy"}
    for row in figures["rows"]:
        assert row["raw_steps_per_s"] > 0
        for a in row["adapters"].values():
            assert a["steps_per_s"] > 0
            assert a["over_raw"] == pytest.approx(a["steps_per_s"] / row["raw_steps_per_s"], rel=0.01)


@pytest.mark.maniskill
def test_policy_in_the_loop_plans_one_chunk_per_8_steps_on_real_maniskill():
    pytest.importorskip("mani_skill", reason="needs ManiSkill: pip install 'l1flow-rl[maniskill]'")
    import torch
    from torch.nn.modules.module import register_module_forward_hook

    from benchmarks.speed.bench_env_throughput import policy_in_loop
    from l1flow_rl import L1FlowActor
    from l1flow_rl.config import load_task_config

    calls = []
    hook = register_module_forward_hook(
        lambda module, args, out: calls.append(1) if isinstance(module, L1FlowActor) else None
    )
    step, close = policy_in_loop(load_task_config("maniskill_pushcube"), torch.device("cpu"), 1)
    try:
        for i in range(17):
            step(i)
    finally:
        hook.remove()
        close()
    assert len(calls) == 3  # steps 0, 8 and 16 start a chunk; the wrapper replays the rest


@pytest.mark.maniskill
@pytest.mark.slow  # ~70 s: a benchmark script, run on purpose (test_train_job covers the train command)
def test_main_job_quick_mode_runs_the_cli_and_checks_its_targets(tmp_path):
    pytest.importorskip("mani_skill", reason="needs ManiSkill: pip install 'l1flow-rl[maniskill]'")
    from benchmarks.success import bench_main_job

    out = tmp_path / "main_job.json"
    argv = ["--quick", "--seeds", "0", "1", "--out", str(out), "--workdir", str(tmp_path / "work")]
    assert bench_main_job.main(argv) == 0
    figures = json.loads(out.read_text())
    assert figures["quick"] is True and figures["seeds"] == [0, 1] and len(figures["runs"]) == 2
    for r in figures["runs"]:
        assert r["steps"] == 4 and r["eval_episodes"] == 2 and r["wall_seconds"] > 0
        assert 0.0 <= r["success_once"] <= 1.0
        assert r["wall_over_budget"] == pytest.approx(r["wall_seconds"] / 480, abs=1e-3)
        assert r["meets_targets"] is False  # 2 episodes can never meet the 100-episode target
    assert figures["success_once_min"] == min(r["success_once"] for r in figures["runs"])
    assert figures["wall_seconds_max"] == max(r["wall_seconds"] for r in figures["runs"])
    assert figures["meets_targets"] is False and out.with_suffix(".png").stat().st_size > 0
    # the runs' seeds reach the CLI: each run directory records its own
    for seed in (0, 1):
        assert f"seed: {seed}\n" in (tmp_path / "work" / f"seed{seed}" / "run" / "config.yaml").read_text()
    from benchmarks.report.success import render_main_job

    table = render_main_job(figures)
    assert table.count("\n| ") == 2 and "the job does not meet its targets" in table  # one row per run
    # --reuse reads the finished runs back instead of training again; a missing run is refused
    again = tmp_path / "again.json"
    work = ["--workdir", str(tmp_path / "work")]
    argv = ["--quick", "--reuse", "--seeds", "0", "1", "--out", str(again), *work]
    assert bench_main_job.main(argv) == 0
    assert json.loads(again.read_text())["runs"][1]["success_once"] == figures["runs"][1]["success_once"]
    argv = ["--quick", "--reuse", "--seeds", "5", "--out", str(again), *work]
    assert bench_main_job.main(argv) == 2
    # CI's guard: exit 1 when a run's test is below it, 0 at or under its figure
    worst = min(r["success_once"] for r in figures["runs"])
    guarded = ["--quick", "--reuse", "--seeds", "0", "1", "--out", str(again), *work]
    assert bench_main_job.main([*guarded, "--guard", str(worst + 0.01)]) == 1
    assert bench_main_job.main([*guarded, "--guard", str(worst)]) == 0
    with pytest.raises(SystemExit):  # the seeds are the script's: a seed= override is refused
        bench_main_job.main(["--quick", "--out", str(again), "seed=3"])


def test_report_does_not_pass_the_collectors_threads_and_load_off_as_the_runs():
    from benchmarks.report.tables import machine_text as _machine

    machine = {"cpu": "Some CPU", "cores": 2, "torch_threads": 2, "load_average_1min": 0.11}

    trained = _machine({"machine": machine, "args": {"collect_only": False}})
    assert trained == "Some CPU, 2 cores, torch threads 2, load 0.11"
    collected = _machine({"machine": machine, "args": {"collect_only": True}})
    assert collected.startswith("Some CPU, 2 cores (where the runs were collected")
    assert "threads 2" not in collected and "0.11" not in collected
    # runs that recorded their machine are described by it, and the rest are counted
    seed = {"machine": {"cpu": "Run CPU", "torch_threads": 1, "load_average_1min": 2.5}}
    tasks = {"t": {"l1flow": {"per_seed": [seed, {**seed, "machine": None}]}}}
    collected = _machine({"machine": machine, "args": {"collect_only": True}, "tasks": tasks})
    assert collected.endswith(
        "the runs: Run CPU, torch threads 1, load 2.5-2.5 as they ended (1 of 2 seed records carry it)"
    )


def test_open_loop_error_reads_each_runs_checkpoint_on_the_same_windows(tmp_path):
    # Two tiny runs of the point-mass double laid out as bench_success lays them out; the benchmark
    # scores both on the same demonstration windows, and DDPM runs also under DDIM-16.
    from doubles.point_mass import (
        POINT_MASS_TASK,  # noqa: F401  (registers the double)
        TASK_OVERRIDES,
    )

    from benchmarks.success import bench_open_loop
    from l1flow_rl.commands.cli import main

    root = tmp_path / "grid"
    for method in ("l1flow", "ddpm"):
        run = root / "point_mass_reach" / method / "seed0"
        args = [
            *TASK_OVERRIDES,
            f"policy={method}",
            "network.down_dims=[16,32]",
            "demos.num=4",
            "train.steps=40",
            "train.batch_size=16",
            "train.warmup_steps=2",
            "eval.episodes=2",
            "eval.num_envs=2",
            "device=cpu",
            f"data_dir={tmp_path / 'data'}",
            f"run_dir={run}",
        ]
        assert main(["train", *args]) == 0
        assert (run / "checkpoints" / "best.pt").is_file()
    out = tmp_path / "open_loop.json"
    argv = ["--root", str(root), "--task", "point_mass_reach", "--policies", "l1flow", "ddpm", "flow"]
    argv += ["--seeds", "0", "--windows", "40", "--quick"]
    assert bench_open_loop.main([*argv, "--out", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert set(figures["runs"]) == {"l1flow", "ddpm", "ddpm_ddim16"}
    assert figures["missing"] == [
        str(root / "point_mass_reach" / "flow" / "seed0" / "checkpoints" / "best.pt")
    ]
    for label, runs in figures["runs"].items():
        r = runs["seed0"]
        assert 0 < r["l1"] < 2 and len(r["l1_per_dim"]) == 2, label  # normalised actions: |error| <= 2
        assert r["steps_compared"] > 0
        assert figures["methods"][label]["l1_mean"] == r["l1"]
    # Same windows, same noise: a second reading of a checkpoint gives the same figure.
    again = tmp_path / "again.json"
    assert (
        bench_open_loop.main([*argv, "--seeds", "0", "--windows", "40", "--quick", "--out", str(again)]) == 0
    )
    assert json.loads(again.read_text())["runs"] == figures["runs"]


@pytest.mark.maniskill
@pytest.mark.slow  # ~15 s: a benchmark script, run on purpose
def test_reinflow_cost_quick_mode_prices_acting_ppo_and_env_stepping(tmp_path):
    pytest.importorskip("mani_skill")
    from benchmarks.finetune import bench_reinflow_cost as bench

    out = tmp_path / "reinflow_cost.json"
    assert bench.main(["--quick", "--envs", "2", "--out", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert figures["quick"] is True and figures["network"] == "mlp" and figures["envs"] == 2
    assert set(figures["wall_ms"]) == {
        "ppo_minibatch",
        "chunk_2nfe_b1",
        "chain_b1",
        "chunk_2nfe_b2",
        "chain_b2",
    }
    per = figures["core_hours_per_million_env_steps"]
    assert all(per[k] > 0 for k in ("env", "acting", "ppo"))
    assert per["total"] == pytest.approx(per["env"] + per["acting"] + per["ppo"], abs=0.005)
    # both cores for 2 hours over the total: the bound the file states
    assert figures["env_steps_in_2h_of_2_cores_at_most"] == pytest.approx(4 * 1e6 / per["total"], rel=0.01)
    assert figures["env"]["workers"]["num_envs"] == 2 and figures["env"]["in_process"]["raw_steps_per_s"] > 0
    from benchmarks.report.finetune import render_reinflow_cost

    table = render_reinflow_cost(figures)
    assert f"| {per['env']:.2f} / {per['acting']:.2f} / {per['ppo']:.2f} / {per['total']:.2f} |" in table
