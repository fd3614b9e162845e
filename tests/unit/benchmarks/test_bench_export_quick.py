"""benchmarks/speed/bench_export_latency.py --quick runs and saves every path with its ratio and match."""

from __future__ import annotations

import json

import pytest


@pytest.mark.slow  # 31 s on 2 busy cores, most of it the ONNX export
def test_bench_export_latency_quick_writes_ratios_and_matches(tmp_path):
    pytest.importorskip("onnxruntime", reason="the ONNX path needs the export extra")
    from benchmarks.speed import bench_export_latency

    out = tmp_path / "export_latency.json"
    assert bench_export_latency.main(["--quick", "--network", "state", "--out", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert figures["quick"] and figures["batch"] == 1 and figures["machine"]["cores"] >= 1
    paths = figures["networks"]["state"]["paths"]
    assert set(paths) == {"eager_actor", "eager_policy", "exported", "onnxruntime"}
    assert paths["eager_actor"]["ratio_to_eager_actor"] == 1.0
    assert all(row["wall_ms"] > 0 and row["ratio_to_eager_actor"] > 0 for row in paths.values())
    assert paths["exported"]["max_abs_diff_from_eager"] == 0.0
    assert paths["onnxruntime"]["max_abs_diff_from_eager"] < 1e-4


def test_the_saved_figures_render_one_row_per_path():
    from pathlib import Path

    from benchmarks.report.speed import render_export_latency

    data = json.loads(
        (Path(__file__).parents[3] / "benchmarks" / "results" / "export_latency.json").read_text()
    )
    text = render_export_latency(data)
    for network, block in data["networks"].items():
        assert f"**{network} network**" in text
        assert sum(
            line.startswith("| ")
            for line in text.split(f"**{network} network**")[1].split("**")[0].splitlines()
        ) == (len(block["paths"]) + 1)
    assert "| `torch.export` program (`policy.pt2`) |" in text
