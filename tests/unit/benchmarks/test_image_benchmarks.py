"""The image benchmarks run end to end in quick mode and record what they compare (never timed here)."""

import json

from benchmarks.speed import bench_image_latency, bench_image_train


def test_image_train_benchmark_quick(tmp_path):
    out = tmp_path / "image_train.json"
    assert bench_image_train.main(["--quick", "--out", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert figures["quick"] is True and set(figures["step_ms"]) == {"buffer", "resident"}
    assert figures["setup"]["rgb_dtype"] == "torch.uint8"
    assert figures["setup"]["rgb_storage"] == "MemoryMappedTensor"
    rate = figures["samples_per_s"]
    assert figures["buffer_over_resident"] == rate["buffer"] / rate["resident"] > 0


def test_image_latency_benchmark_quick(tmp_path):
    out = tmp_path / "image_latency.json"
    assert bench_image_latency.main(["--quick", "--out", str(out)]) == 0
    block = json.loads(out.read_text())["inference"]["batch1"]
    assert set(block["ms"]) == {"actor", "floor"}
    assert block["actor_over_floor"] == block["ms"]["actor"]["wall_ms"] / block["ms"]["floor"]["wall_ms"]
