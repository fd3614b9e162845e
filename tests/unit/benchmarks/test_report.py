"""benchmarks.report: RESULTS.md and the README's summary come from the saved JSON only, and --check
names what is out of date."""

import json
import re

import pytest

from benchmarks import report
from benchmarks.report.defaults_evidence import evidence_table
from benchmarks.speed import bench_latency


def _toy(regression_modes: int) -> dict:
    """A multimodal.json as bench_multimodal saves it: two methods on one two-mode family."""

    def method(nfe, hit, off):
        return {"nfe": nfe, "modes_hit": hit, "num_modes": 2, "share_neither": off, "balance": 0.5}

    methods = {"l1flow": method(2, 2, 0.01), "regression": method(1, regression_modes, 0.97)}
    return {
        "steps": 100,
        "machine": {"cpu": "Some CPU", "cores": 2, "torch_threads": 1},
        "families": {"opposite_sines": {"num_modes": 2, "methods": methods}},
    }


def _setup(tmp_path, results_files: dict) -> tuple:
    results = tmp_path / "benchmarks" / "results"
    results.mkdir(parents=True)
    for name, data in results_files.items():
        (results / name).write_text(json.dumps(data))
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{report.BEGIN}\nstale\n{report.END}\noutro\n")
    doc = tmp_path / "benchmarks" / "RESULTS.md"
    argv = ["--readme", str(readme), "--results", str(results), "--out", str(doc)]
    return results, readme, doc, argv


def test_report_writes_results_and_the_readme_summary_from_saved_results_only(tmp_path, capsys):
    results, readme, doc, argv = _setup(tmp_path, {"somebody_new.json": {}})
    assert (
        bench_latency.main(["--quick", "--no-train", "--no-peers", "--out", str(results / "latency.json")])
        == 0
    )
    figures = json.loads((results / "latency.json").read_text())
    (results / "latency.json").write_text(json.dumps({**figures, "quick": False}))
    (results / "latency_image.json").write_text(json.dumps(figures))  # a --quick run: never reported
    mlp = {"kind": "mlp", "name": "mlp", "hidden_dims": [512] * 4, "parameters": 926784}
    (results / "latency_mlp.json").write_text(json.dumps({**figures, "quick": False, "network": mlp}))

    assert report.main([*argv, "--check"]) == 1
    out = capsys.readouterr().out
    assert "results summary between the markers is out of date" in out and f"{doc}: missing" in out
    assert report.main(argv) == 0

    summary = readme.read_text()
    assert summary.startswith("intro\n") and summary.endswith("outro\n") and "stale" not in summary
    ms = figures["inference"]["batch1"]["ms"]["l1flow_2nfe"]["wall_ms"]
    slowdown = figures["inference"]["batch1"]["slowdown_vs_l1flow"]["ddim16"]
    # the claims row of the speed claim, its numbers from the file, and a link to the full document
    assert f"ms per chunk | DDIM-16 {slowdown:.3g}× slower" in summary
    assert "[RESULTS.md](benchmarks/RESULTS.md)" in summary
    assert "| l1flow_2nfe |" not in summary  # the file's own tables stay in RESULTS.md

    text = doc.read_text()
    assert f"| l1flow_2nfe | 2 | {ms:.3g} (1×) |" in text  # the number comes from the file
    assert "### Per-chunk latency, every sampler" in text
    # the distillation comparison's samplers are rows, and the MLP's file is a column of its own
    assert "| cp3 | 3 | " in text and "| edm_heun18 | 35 | " in text and "| onedp1 | 1 | " in text
    assert "| state, cpu, batch1 | mlp, cpu, batch1 |" in text and "MLP 512/512/512/512" in text
    # the section names its file (linked from RESULTS.md's folder), when and where it was measured,
    # and the command and commit that rerun it, which the script recorded
    record = figures["provenance"]
    assert record["command"].startswith("python -m benchmarks.speed.bench_latency --quick --no-train")
    assert record["config"]["quick"] is True and record["config"]["out"] == str(results / "latency.json")
    assert re.fullmatch(r"[0-9a-f]{40}(-dirty)?", record["commit"])
    source = next(line for line in text.splitlines() if "[`latency.json`](results/latency.json)" in line)
    assert f"measured: {record['measured_at']}; machine: " in source
    assert f"command: `{record['command']}`; commit `{record['commit'][:12]}`" in source
    assert "`somebody_new.json`" in text  # a file without a renderer is named, not dropped
    assert "latency_image" not in text
    assert report.main([*argv, "--check"]) == 0


def test_check_names_each_out_of_date_section(tmp_path, capsys):
    results, readme, doc, argv = _setup(tmp_path, {"multimodal.json": _toy(regression_modes=0)})
    assert report.main(argv) == 0
    assert "| regression | 1 | 0/2 | 0.97 | 0.5 |" in doc.read_text()
    assert report.main([*argv, "--check"]) == 0

    # a re-run changed the figures: the file's section and the claims (README and RESULTS.md) are stale
    (results / "multimodal.json").write_text(json.dumps(_toy(regression_modes=2)))
    capsys.readouterr()
    assert report.main([*argv, "--check"]) == 1
    out = capsys.readouterr().out
    assert f"{readme}: the results summary between the markers is out of date" in out
    stale = next(line for line in out.splitlines() if line.startswith(f"{doc}: out of date in"))
    assert "'Multi-modality (toy)'" in stale
    assert "'The paper's claims, as measured here'" in stale
    assert "Simulators" not in stale and "'Results'" not in stale  # untouched sections are not named

    # a hand edit of RESULTS.md is named too, and rebuilding restores it
    assert report.main(argv) == 0
    doc.write_text(
        doc.read_text().replace("## Multi-modality\n", "## Multi-modality\n\nA hand-typed note.\n")
    )
    assert report.main([*argv, "--check"]) == 1
    assert "out of date in 'Multi-modality'" in capsys.readouterr().out
    assert report.main(argv) == 0 and report.main([*argv, "--check"]) == 0


def test_stale_sections_names_added_removed_and_reordered_sections():
    old = "# A\nx\n## B\ny\n## C\nz\n"
    assert report.stale_sections(old, old) == []
    assert report.stale_sections(old, "# A\nx\n## B\nchanged\n## C\nz\n") == ["B"]
    assert report.stale_sections(old, "# A\nx\n## C\nz\n") == ["B"]  # removed
    assert report.stale_sections(old, old + "## D\nw\n") == ["D"]  # added
    assert report.stale_sections(old, "# A\nx\n## C\nz\n## B\ny\n") == ["(the order of the sections)"]


def test_readme_without_markers_is_refused(tmp_path, capsys):
    _, readme, _, argv = _setup(tmp_path, {})
    readme.write_text("no markers\n")
    assert report.main(argv) == 2
    assert "no results markers" in capsys.readouterr().out
    assert readme.read_text() == "no markers\n"


def test_defaults_evidence_reads_its_figures_from_the_saved_files(tmp_path):
    assert evidence_table(tmp_path) is None  # nothing saved, no table
    run = {"steps": 2500, "eval_episodes": 50, "success_once": 0.84, "success_once_ci95": [0.71, 0.92]}
    main_job = {
        "budget_seconds": 900,
        "wall_seconds_max": 480.4,
        "wall_over_budget_max": 480.4 / 900,
        "runs": [run, {**run, "success_once": 0.9, "success_once_ci95": None}],
    }
    (tmp_path / "main_job.json").write_text(json.dumps(main_job))
    curve = [[1000, 0.4], [2000, 0.8]]
    stats = {"mean": 0.75, "n": 2}
    block = {"success_once": stats, "per_seed": [], "curves": [curve, [[1000, 0.6], [2000, 0.7]]]}
    success = {"args": {"demos": 300, "steps": 2000}, "tasks": {"maniskill_stackcube": {"l1flow": block}}}
    (tmp_path / "success_stackcube.json").write_text(json.dumps(success))
    (tmp_path / "success_pusht.json").write_text(json.dumps({"quick": True}))  # a --quick file: no row
    table = evidence_table(tmp_path)
    rows = table.splitlines()[2:]
    assert len(rows) == 2
    assert (
        "2,500 training steps and a 50-episode test evaluation in at most 480 s (0.53 of the 15-minute "
        "budget) over 2 seeds" in rows[0]
    )
    assert "success_once 0.84 [0.71, 0.92], 0.90 | `main_job.json` |" in rows[0]
    # the curve is the mean over seeds at each validation step
    assert (
        "300 demonstrations, 2 seeds: validation success_once 0.50 at 1,000, 0.75 at 2,000 steps" in rows[1]
    )
    assert rows[1].endswith("| `success_stackcube.json` |")


def test_readme_stays_short_its_test_command_is_cis_and_its_snippet_runs(capsys):
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    readme = (root / "README.md").read_text()
    assert len(readme.splitlines()) <= 300
    commands = re.findall(r"```bash\n(.*?)\n```", readme, re.S)[:2]
    assert commands == [
        "./install.sh && .venv/bin/l1flow-rl train",
        "./install.sh all && .venv/bin/python -m pytest",
    ]
    assert commands[1] in (root / ".ci" / "run").read_text().splitlines()
    snippet = re.findall(r"```python\n(.*?)```", readme, re.S)[0]
    exec(compile(snippet, "README.md", "exec"), {})
    assert "torch.Size([1, 8, 4])" in capsys.readouterr().out


def _finetune_file(start_test: float, online: list[float], control: list[float], data_steps=None) -> dict:
    """A finetune_online_*.json as bench_finetune_online saves it, cut to what the overview reads."""
    seeds = {
        str(s): {
            "test": {"success_once": t},
            **({"data_cost": {"env_steps": data_steps}} if data_steps else {}),
        }
        for s, t in enumerate(control)
    }
    curve = [
        {"env_steps": 0, "mean": 0.3, "min": 0.3, "max": 0.3},
        {"env_steps": 20_000, "mean": 0.5, "min": 0.4, "max": 0.6},
    ]
    return {
        "controls": {
            "bc_start": {"run_dir": "runs/start", "test": {"success_once": start_test}},
            "continued_bc": {
                "seeds": seeds,
                "test": {"success_once": sum(control) / len(control)},
                "updates": 800,
            },
        },
        "algorithms": {
            "filtered_bc": {
                "runs": {str(s): {"test": {"success_once": t}} for s, t in enumerate(online)},
                "aggregate": {"curve": curve},
            }
        },
    }


def test_finetune_overview_reads_each_arm_from_its_file_and_refuses_mixed_starts(tmp_path):
    from benchmarks.report.finetune_overview import Arm, overview_figures, overview_table

    headline = {
        "Toy (10 episodes)": [
            Arm(
                "online",
                "finetune_online_a.json",
                "algorithms.filtered_bc",
                ("finetune_online_a.json", "controls.continued_bc"),
            ),
            Arm("continued BC", "finetune_online_a.json", "controls.continued_bc"),
            Arm(
                "replays",
                "finetune_online_b.json",
                "controls.continued_bc",
                ("finetune_online_a.json", "controls.continued_bc"),
            ),
        ]
    }
    assert overview_table(tmp_path, headline) is None and overview_figures(tmp_path, headline) == []
    (tmp_path / "finetune_online_a.json").write_text(
        json.dumps(_finetune_file(0.25, [0.5, 0.6, 0.7], [0.2, 0.3]))
    )
    (tmp_path / "finetune_online_b.json").write_text(json.dumps(_finetune_file(0.25, [], [0.9, 0.8], 12_000)))
    table = overview_table(tmp_path, headline)
    rows = [r for r in table.splitlines() if r.startswith("| ")][1:]
    # the arm by its label, its file by a number listed under the table
    assert rows[0] == (
        "| Toy (10 episodes) (0.25) | online | 3 | 20k | 0.60 (0.50 / 0.60 / 0.70) | +35 | +35 | 1 |"
    )
    assert rows[1] == "|  | continued BC | 2 | 0 | 0.25 (0.20 / 0.30) | +0 | – | 1 |"
    assert rows[2] == "|  | replays | 2 | 12k of replays | 0.85 (0.90 / 0.80) | +60 | +60 | 2 |"
    assert table.endswith("Files (`finetune_online_<name>.json`): 1 `a`, 2 `b`.")
    (figure,) = overview_figures(tmp_path, headline)
    assert figure.name == "finetune_overview_toy_10_episodes.png" and figure.stat().st_size > 0

    (tmp_path / "finetune_online_b.json").write_text(json.dumps(_finetune_file(0.3, [], [0.9], 12_000)))
    with pytest.raises(ValueError, match=r"finetune_online_b.json starts from runs/start \(test 0.3\)"):
        overview_table(tmp_path, headline)
    missing = {"Toy": [Arm("qc", "finetune_online_a.json", "algorithms.qc")]}
    with pytest.raises(
        KeyError, match=r"finetune_online_a.json: no 'algorithms.qc' \(it has \['filtered_bc'\]\)"
    ):
        overview_table(tmp_path, missing)
    unsaved = {
        "Toy": [
            Arm("x", "finetune_online_a.json", "controls.continued_bc"),
            Arm("y", "gone.json", "controls.x"),
        ]
    }
    with pytest.raises(FileNotFoundError, match=r"gone.json: named by HEADLINE \('y'\) but not saved"):
        overview_table(tmp_path, unsaved)


def test_every_headline_arm_of_the_saved_results_reads_and_the_readme_holds_their_table():
    from pathlib import Path

    from benchmarks.report.finetune_overview import HEADLINE, overview_table

    root = Path(__file__).resolve().parents[3]
    table = overview_table(root / "benchmarks" / "results")
    assert len([r for r in table.splitlines() if r.startswith("| ")]) == 1 + sum(map(len, HEADLINE.values()))
    readme = (root / "README.md").read_text()
    assert readme.index(report.FT_BEGIN) < readme.index(table.splitlines()[2]) < readme.index(report.FT_END)


def test_report_rebuilds_the_readmes_finetune_block_and_check_flags_it(tmp_path, capsys):
    _, readme, _, argv = _setup(tmp_path, {})
    readme.write_text(readme.read_text() + f"ft\n{report.FT_BEGIN}\nstale table\n{report.FT_END}\nend\n")
    assert report.main(argv) == 0
    text = readme.read_text()
    assert (
        "stale table" not in text and "No fine-tuning results saved yet." in text and text.endswith("end\n")
    )
    assert report.main([*argv, "--check"]) == 0
    readme.write_text(text.replace("No fine-tuning results saved yet.", "typed by hand"))
    assert report.main([*argv, "--check"]) == 1
    assert "fine-tuning table between the markers is out of date" in capsys.readouterr().out


def test_arm_names_say_the_algorithm_how_it_ran_and_its_overrides():
    from benchmarks.report.finetune_overview import arm_name

    overrides = ["online.action_noise=0.02", "finetune.filtered_bc.mask_padding=true"]
    assert arm_name("algorithms", "filtered_bc", {}, overrides) == (
        "filtered BC online, action noise 0.02, padding masked"
    )
    qc = ["finetune.qc.num_samples=8", "finetune.qc.freeze_flow=true", "online.updates_per_step=0.1"]
    assert arm_name("controls", "qc_offline", {"updates": 11500}, qc) == (
        "QC's TD-only arm, 11,500 updates, best of 8, flow frozen, 0.1 updates per env step"
    )
    assert arm_name("controls", "continued_bc_last", {"updates": 4000}, ["demos.shifted_replays=200"]) == (
        "200 shifted replays, then continued BC, 4,000 updates, last weights tested"
    )
    assert arm_name("controls", "continued_bc_8k", {}, None) == "continued BC, 8,000 updates"
    assert arm_name("controls", "fql_last", {}, ["offline.steps=3000"]) == (
        "FQL online, last weights tested, 3,000 offline updates first"
    )
    # an override without a phrase is named as written; one switched off is not named
    assert arm_name("algorithms", "dsrl", {}, ["x.y=1", "finetune.filtered_bc.mask_padding=false"]) == (
        "DSRL online, `x.y=1`"
    )
    # what the offline phase trains is named either way (the flowq preset trains the critics alone);
    # the validation cadence changes nothing trained and is not named
    flowq = ["offline.steps=2000", "offline.critic_only=false", "offline.eval_every=5000"]
    assert arm_name("algorithms", "flowq", {}, flowq) == (
        "flowq online, 2,000 offline updates first, actor trained offline too"
    )
    assert (
        arm_name("algorithms", "flowq", {}, ["offline.critic_only=true"])
        == "flowq online, critics alone offline"
    )


def test_the_arms_table_holds_every_arm_of_every_file_grouped_by_start(tmp_path):
    from pathlib import Path

    from benchmarks.report.finetune_overview import Arm, arms_table

    a = _finetune_file(0.25, [0.5, 0.6, 0.7], [0.2, 0.3])
    a["algorithms"]["filtered_bc"]["budget_overrides"] = ["online.action_noise=0.02"]
    other = _finetune_file(0.4, [0.5], [0.45])
    other["controls"]["bc_start"]["run_dir"] = "runs/other"
    files = [(Path("finetune_online_a.json"), a), (Path("finetune_online_z.json"), other)]
    headline = {"Toy (10 episodes)": [Arm("online", "finetune_online_a.json", "algorithms.filtered_bc")]}
    rows = [r for r in arms_table(files, headline).splitlines() if r.startswith("| ")][1:]
    assert rows == [
        "| Toy (10 episodes) (0.25) | continued BC, 800 updates | 2 | 0 | 0.25 (0.20 / 0.30) | – | +0 | 1 |",
        "|  | filtered BC online, action noise 0.02 | 3 | 20k | 0.60 (0.50 / 0.60 / 0.70) "
        "| 0k: 0.30, 20k: 0.50 | +35 | 1 |",
        # a start the headline does not name is named by its run
        "| `runs/other` (0.40) | continued BC, 800 updates | 1 | 0 | 0.45 (0.45) | – | +5 | 2 |",
        "|  | filtered BC online | 1 | 20k | 0.50 (0.50) | 0k: 0.30, 20k: 0.50 | +10 | 2 |",
    ]


def test_the_saved_results_make_one_section_per_table_and_leave_no_file_out():
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    text = (root / "benchmarks" / "RESULTS.md").read_text()
    headings = [line for line in text.splitlines() if line.startswith("#")]
    assert len(headings) == len(set(headings))  # no table repeated per file
    assert len(text.splitlines()) <= 945  # one section per table, not per trial: a bound on growth
    assert "## Other saved results" not in text  # every saved file is in a published table
    assert text.count("### Online fine-tuning") == 1


def test_a_one_file_section_puts_its_status_and_source_in_one_paragraph_and_several_files_list_theirs(
    tmp_path,
):
    from benchmarks.report.build import Section, _section

    section = Section("x*.json", "X", render=lambda data: f"| v |\n|---|\n| {data['v']} |")
    files = [(tmp_path / "x1.json", {"v": 1, "note": "its own words"}), (tmp_path / "x2.json", {"v": 2})]
    one = _section(section, files[:1], tmp_path / "RESULTS.md", repo=tmp_path)
    assert one[:2] == ["### X", ""]
    assert one[2].startswith("Status: unverified") and " Source: [`x1.json`](x1.json)" in one[2]
    assert one[3:5] == ["", "| v |\n|---|\n| 1 |\n\nits own words"]
    two = _section(section, files, tmp_path / "RESULTS.md", repo=tmp_path)
    assert two[2].startswith("Status: unverified") and "Source" not in two[2]
    assert [line for line in two if line.startswith("Source: ")] == [
        line for line in two if "[`x1.json`]" in line or "[`x2.json`]" in line
    ]
    assert len([line for line in two if line.startswith("Source: ")]) == 2


def test_a_files_note_continues_the_prose_that_ends_its_block_and_follows_a_table_on_its_own(tmp_path):
    from benchmarks.report.build import Section, _section

    prose = Section("x*.json", "X", render=lambda data: f"| v |\n|---|\n| {data['v']} |\n\nThe verdict.")
    files = [(tmp_path / "x1.json", {"v": 1, "note": "Its own words."})]
    assert _section(prose, files, tmp_path / "RESULTS.md", repo=tmp_path)[4] == (
        "| v |\n|---|\n| 1 |\n\nThe verdict. Its own words."
    )
    table = Section("x*.json", "X", render=lambda data: f"| v |\n|---|\n| {data['v']} |\n")
    assert (
        _section(table, files, tmp_path / "RESULTS.md", repo=tmp_path)[4]
        == "| v |\n|---|\n| 1 |\n\nIts own words."
    )


def test_the_main_jobs_block_names_the_command_a_variant_ran():
    from benchmarks.report.success import render_main_job

    run = {
        "seed": 0,
        "wall_seconds": 140.0,
        "wall_over_budget": 140 / 480,
        "success_once": 0.92,
        "eval_episodes": 100,
    }
    d = {
        "runs": [run],
        "budget_seconds": 480,
        "meets_targets": False,
        "success_once_mean": 0.92,
        "success_once_min": 0.92,
        "wall_seconds_max": 140.0,
        "target_success_once": 0.95,
        "target_episodes": 100,
        "overrides": ["eval.episodes=100"],
    }
    assert "ManiSkill PushCube (state), the plain `l1flow-rl train`, each run" in render_main_job(d)
    d["overrides"] = ["eval.episodes=100", "network=mlp"]
    text = render_main_job(d)
    assert "ManiSkill PushCube (state), `l1flow-rl train network=mlp`, each run" in text
    assert "the job does not meet its targets" in text


def test_a_merged_sections_notes_follow_their_own_source_lines(tmp_path):
    from benchmarks.report.build import Section, _section

    section = Section("x*.json", "X", render=lambda files: "| n |\n|---|\n| 2 |", merged=True)
    files = [
        (tmp_path / "x1.json", {"note": "first words"}),
        (tmp_path / "x2.json", {}),
        (tmp_path / "x3.json", {"note": "third words"}),
    ]
    parts = _section(section, files, tmp_path / "RESULTS.md", repo=tmp_path)
    assert parts[-1] == "" and [p[:3] for p in parts[-4:-1]] == ["1. ", "2. ", "3. "]
    assert parts[-4].startswith("1. [`x1.json`]") and parts[-4].endswith(" first words")
    assert parts[-2].endswith(" third words") and "words" not in parts[-3]
    assert not any(p.startswith("- `") for p in parts)  # no second list of the same files
    no_notes = _section(section, files[1:2], tmp_path / "RESULTS.md", repo=tmp_path)
    assert no_notes[-2].startswith("1. ") and no_notes[-1] == ""


def _seed_file(seeds: dict[int, tuple[list[float], float]], overrides: list[str], start_test=0.3) -> dict:
    """A file of one online arm: seed -> (validation at 0 and 20k env steps, test), its last weights."""
    runs = {
        str(s): {"validation": [{"env_steps": 20_000 * k, "success_once": v} for k, v in enumerate(val)]}
        | {"test": {"success_once": test}}
        for s, (val, test) in seeds.items()
    }
    last = {str(s): {"test": {"success_once": test - 0.1}} for s, (_, test) in seeds.items()}
    return {
        "controls": {
            "bc_start": {"run_dir": "runs/start", "test": {"success_once": start_test}},
            "flowq_last": {"seeds": last, "test": {"success_once": 0.0}},
        },
        "algorithms": {"flowq": {"budget_overrides": overrides, "runs": runs, "aggregate": {"curve": []}}},
    }


def test_an_arm_joins_the_seeds_of_several_files_of_one_command_and_refuses_other_settings(tmp_path):
    from benchmarks.report.finetune_overview import Arm, arms_table, overview_table

    a = _seed_file({0: ([0.3, 0.5], 0.6), 2: ([0.3, 0.7], 0.5)}, ["online.updates_per_step=0.5"])
    b = _seed_file({1: ([0.3, 0.3], 0.7)}, ["online.updates_per_step=0.5"])
    for name, data in (("finetune_online_a.json", a), ("finetune_online_b.json", b)):
        (tmp_path / name).write_text(json.dumps(data))
    arm = Arm("flow-Q", "finetune_online_a.json", "algorithms.flowq", more=("finetune_online_b.json",))
    headline = {"Toy": [arm]}
    rows = [r for r in overview_table(tmp_path, headline).splitlines() if r.startswith("| ")][1:]
    # seeds in order across the files, both files numbered
    assert rows == ["| Toy (0.30) | flow-Q | 3 | 20k | 0.60 (0.60 / 0.70 / 0.50) | +30 | – | 1, 2 |"]
    files = [(tmp_path / "finetune_online_a.json", a), (tmp_path / "finetune_online_b.json", b)]
    rows = [r for r in arms_table(files, headline).splitlines() if r.startswith("| ")][1:]
    # one row: the curve recomputed over the three seeds, the last weights of all three
    assert rows == [
        "| Toy (0.30) | flowq online, 0.5 updates per env step | 3 | 20k | 0.60 (0.60 / 0.70 / 0.50; "
        "last weights 0.50) | 0k: 0.30, 20k: 0.50 | +30 | 1, 2 |"
    ]
    # without the headline's join, each file is a row of its own
    assert len([r for r in arms_table(files, {}).splitlines() if r.startswith("| ")][1:]) == 2

    refusals = [
        (_seed_file({1: ([0.3, 0.3], 0.7)}, ["online.updates_per_step=1"]), "must share its settings"),
        (_seed_file({1: ([0.3, 0.3], 0.7)}, ["online.updates_per_step=0.5"], 0.4), "must share its start"),
        (_seed_file({2: ([0.3, 0.3], 0.7)}, ["online.updates_per_step=0.5"]), "seed 2 of algorithms.flowq"),
    ]
    for other, message in refusals:
        (tmp_path / "finetune_online_b.json").write_text(json.dumps(other))
        with pytest.raises(ValueError, match=message):
            overview_table(tmp_path, headline)
