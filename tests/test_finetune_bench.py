"""benchmarks/bench_flow_q.py end to end in its quick mode (tiny budgets on PushCube): every arm runs
and the JSON the README would read holds each arm's success, budget and the online curve."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("mani_skill", reason="needs ManiSkill: pip install 'l1flow-rl[maniskill]'")

from benchmarks import bench_flow_q

pytestmark = [pytest.mark.maniskill, pytest.mark.slow]


def test_quick_mode_runs_every_arm_and_saves_json_and_plot(tmp_path):
    out = tmp_path / "flow_q.json"
    args = [
        "--quick",
        "--root",
        str(tmp_path / "runs"),
        "--data-dir",
        str(tmp_path / "data"),
        "--out",
        str(out),
    ]
    assert bench_flow_q.main(args) == 0
    figures = json.loads(out.read_text())
    assert figures["quick"] is True
    assert set(figures["arms"]) == {"bc", "flowq_offline", "flowq_online", "bc_continued"}
    for arm in figures["arms"].values():
        assert 0.0 <= arm["success_once"] <= 1.0 and arm["episodes"] == 2
    assert figures["arms"]["flowq_online"]["env_steps"] == 40
    assert figures["arms"]["flowq_offline"]["env_steps"] == 0
    assert figures["budget"]["bc_continued_steps"] == 20 + 4 + 4  # BC + offline + online updates
    assert figures["arms"]["bc_continued"]["updates"] == 28
    curve = figures["online_curve"][0]
    assert [e["env_steps"] for e in curve["evaluations"] if e["phase"] == "online"] == [20]
    assert out.with_suffix(".png").stat().st_size > 1000
    # a second call reads the finished runs back instead of repeating them
    assert bench_flow_q.main(args) == 0
