"""The second table's section and its claim: the rows in the saved order with their figures, and the
verdict's rule over L1 Flow's interval and the training each distilled row needed."""

from __future__ import annotations

import json

import pytest

from benchmarks.report.claims import claims_table
from benchmarks.report.distillation import distillation_claim_rows, render_distillation


def _row(method: str, nfe: int, success: float, to_90: list[int] | None, teacher: int = 0) -> dict:
    per_seed = [{"seed": 0, "success_once": success, "value": success, "episodes": 100}]
    return {
        "method": method,
        "nfe": nfe,
        "success_once": {"mean": success, "n": 1},
        "per_seed": per_seed,
        "training_steps": [teacher + 1000],
        "teacher_steps": [teacher],
        "steps_to_90pct_of_best_with_teacher": to_90,
        "latency_batch1_ms": {"wall_ms": 2.0 * nfe, "cpu_ms": 2.0 * nfe},
        "latency_vs_l1flow": nfe / 2,
    }


def _file(tmp_path, l1: float, cp: float, cp_steps: int) -> None:
    rows = {
        "edm": _row("DP (EDM)", 35, 0.9, [9000]),
        "consistency": _row("Consistency Policy", 1, cp, [cp_steps], teacher=12000),
        "l1flow": _row("L1 Flow", 2, l1, [1000]),
    }
    args = {"demos": 100, "network": "mlp", "seeds": [0], "eval_episodes": 100, "latency_rounds": 30}
    data = {"task": "robosuite_can", "args": args, "rows": rows, "missing_rows": ["onedp_d"]}
    (tmp_path / "distillation_robosuite_can.json").write_text(json.dumps(data))


def _load(path):
    return json.loads(path.read_text())


@pytest.mark.parametrize(
    ("l1", "cp", "cp_steps", "verdict"),
    [
        (0.90, 0.91, 6000, "holds"),  # within the interval, 6x the training
        (0.90, 0.91, 3000, "comparable or better success, with 3× less training at the least (paper: 5-7×)"),
        (0.90, 0.91, 800, "comparable or better success; not less training than Consistency Policy 1"),
        (0.50, 0.95, 6000, "below Consistency Policy 1"),  # 0.50/100 lies wholly below 0.95/100
    ],
)
def test_the_fifth_claims_verdict_follows_its_rule(tmp_path, l1, cp, cp_steps, verdict):
    _file(tmp_path, l1, cp, cp_steps)
    (row,) = distillation_claim_rows(tmp_path, _load)
    assert row[0] == "comparable to distillation-based methods with 5-7× less training"
    assert row[-1] == verdict
    assert "1,000 steps to 90 % of best" in row[2]
    assert "Consistency Policy 1 NFE:" in row[3]
    assert f"| {verdict} |" in claims_table(tmp_path)  # and it joins the summary's table


def test_the_section_shows_each_row_with_its_teacher_and_the_rows_left_out(tmp_path):
    _file(tmp_path, 0.9, 0.8, 6000)
    text = render_distillation(_load(tmp_path / "distillation_robosuite_can.json"))
    lines = [line for line in text.splitlines() if line.startswith("| ") and "`" in line]
    assert [line.split(" | ")[1] for line in lines] == ["`edm`", "`consistency`", "`l1flow`"]
    assert "| 13,000 (12,000 teacher) | 6,000 | 2 (0.5×) |" in lines[1]
    assert "Rows without a finished evaluation: `onedp_d`." in text


def test_pushts_score_decides_by_its_mean_and_heads_each_row(tmp_path):
    _file(tmp_path, 0.9, 0.9, 6000)
    path = tmp_path / "distillation_robosuite_can.json"
    data = _load(path)
    for label, score in (("edm", 0.7), ("consistency", 0.8), ("l1flow", 0.75)):
        data["rows"][label].update(metric="score", score={"mean": score, "n": 1})
    path.write_text(json.dumps(data))
    (row,) = distillation_claim_rows(tmp_path, _load)
    assert row[2].startswith("score 0.750") and row[-1] == "below Consistency Policy 1"
    assert "| score 0.800 |" in render_distillation(data)
