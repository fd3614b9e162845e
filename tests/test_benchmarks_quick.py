"""The benchmark scripts run end to end in their quick mode and save what the README's report reads.
Speed is never asserted here (figures come from the scripts' own runs); structure and NFE are."""

import json

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
