"""The benchmark scripts run end to end in their quick mode and save what the README's report reads.
Speed is never asserted here (figures come from the scripts' own runs); structure and NFE are."""

import json

import pytest

from benchmarks import bench_latency


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
    assert set(figures["train_step_ms"]["ms"]) == {"l1flow_2nfe", "vflow_euler10", "ddpm100", "regression"}


def test_multimodal_quick_mode_reports_every_family_and_evaluation(tmp_path):
    from benchmarks import bench_multimodal

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


def test_report_builds_the_readme_section_from_saved_results_only(tmp_path):
    from benchmarks import report

    results = tmp_path / "results"
    assert (
        bench_latency.main(["--quick", "--no-train", "--no-peers", "--out", str(results / "latency.json")])
        == 0
    )
    figures = json.loads((results / "latency.json").read_text())
    (results / "latency.json").write_text(json.dumps({**figures, "quick": False}))
    (results / "somebody_new.json").write_text("{}")
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{report.BEGIN}\nstale\n{report.END}\noutro\n")
    assert report.main(["--readme", str(readme), "--results", str(results), "--check"]) == 1
    assert report.main(["--readme", str(readme), "--results", str(results)]) == 0
    text = readme.read_text()
    assert text.startswith("intro\n") and text.endswith("outro\n") and "stale" not in text
    ms = figures["inference"]["batch1"]["ms"]["l1flow_2nfe"]["wall_ms"]
    assert f"| l1flow_2nfe | 2 | {ms:.3g} |" in text  # the number comes from the file
    assert "`somebody_new.json`" in text  # a file without a renderer is named, not dropped
    assert report.main(["--readme", str(readme), "--results", str(results), "--check"]) == 0
