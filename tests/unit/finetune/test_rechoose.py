"""Saved fine-tuning results re-read under the "start" rule: a seed chosen on a lead within the start's
standard error gets the start's test figure, its measured pick kept beside it; the arm's mean follows."""

from __future__ import annotations

import json

import pytest

from benchmarks.finetune.rechoose import main, rechoose


def _seed(values, test, step_chosen):
    evaluations = [{"step": 2000 * i, "success_once": v} for i, v in enumerate(values)]
    return {
        "test": {
            "success_once": test,
            "episodes": 100,
            "selection": {
                "step": step_chosen,
                "value": max(values),
                "rule": "highest validation success_once, the earliest of equals",
                "seeds": {"first": 10000, "episodes": 50},
                "evaluations": evaluations,
            },
        },
        "validation": [{"env_steps": 2000 * i, "success_once": v} for i, v in enumerate(values)],
    }


def _file():
    start = {
        "success_once": 0.53,
        "success_at_end": 0.5,
        "episodes": 100,
        "ci95": {"success_once": [0.43, 0.62]},
    }
    return {
        "controls": {
            "bc_start": {"run_dir": "bc", "test": start},
            "continued_bc": {
                "seeds": {
                    "0": _seed([0.54, 0.50, 0.56], 0.41, 4000),
                    "1": _seed([0.54, 0.70, 0.60], 0.66, 2000),
                },
                "test": {"success_once": 0.535, "min": 0.41, "max": 0.66, "episodes": 100},
            },
            "continued_bc_last": {"seeds": {"0": _seed([0.54, 0.50, 0.56], 0.41, 4000)}},
        },
        "algorithms": {"flowq": {"runs": {"0": _seed([0.54, 0.56, 0.58], 0.49, 4000)}}},
    }


def test_a_lead_within_the_start_s_error_gives_the_start_s_test():
    data = _file()
    moved = rechoose(data)
    assert moved == ["flowq seed 0", "continued_bc seed 0"]  # 0.04 and 0.02 over 0.54 (error 0.070)
    seed0 = data["controls"]["continued_bc"]["seeds"]["0"]
    assert seed0["test"]["success_once"] == 0.53 and seed0["test"]["selection"]["step"] == 0
    assert seed0["rechosen"]["measured_pick"] == {"step": 4000, "validation": 0.56, "test": 0.41}
    assert "0.070" in seed0["test"]["selection"]["rule"]
    # seed 1 led by 0.16: its pick stands; the arm's mean is over the re-chosen seeds
    assert data["controls"]["continued_bc"]["seeds"]["1"]["test"]["success_once"] == 0.66
    assert data["controls"]["continued_bc"]["test"]["success_once"] == pytest.approx((0.53 + 0.66) / 2)
    assert data["algorithms"]["flowq"]["aggregate"]["test_mean"] == 0.53
    # last weights are no choice, and the start is not re-read
    assert data["controls"]["continued_bc_last"]["seeds"]["0"]["test"]["success_once"] == 0.41
    assert rechoose(data) == []  # once re-read, nothing moves again


def test_check_fails_until_the_files_are_re_read(tmp_path, capsys):
    (tmp_path / "finetune_online_x.json").write_text(json.dumps(_file()))
    assert main(["--results", str(tmp_path), "--check"]) == 1
    assert (
        "finetune_online_x.json: flowq seed 0, continued_bc seed 0 keep their start"
        in capsys.readouterr().out
    )
    assert main(["--results", str(tmp_path)]) == 0
    assert main(["--results", str(tmp_path), "--check"]) == 0
    saved = json.loads((tmp_path / "finetune_online_x.json").read_text())
    assert saved["algorithms"]["flowq"]["runs"]["0"]["rechosen"]["measured_pick"]["test"] == 0.49


def test_every_saved_fine_tuning_file_is_read_under_the_start_rule():
    from benchmarks.finetune.rechoose import RESULTS

    files = sorted(RESULTS.glob("finetune_online_*.json"))
    assert files
    unread = {f.name: moved for f in files if (moved := rechoose(json.loads(f.read_text())))}
    assert unread == {}, "run python -m benchmarks.finetune.rechoose"
