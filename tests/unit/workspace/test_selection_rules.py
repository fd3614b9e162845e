"""Which validated model a run ships: the highest validation figure, of equals the latest (training)
or the earliest; under fine-tuning's ``"start"`` rule the first evaluation (the BC start) is kept
unless a later model validates more than one standard error above it."""

from __future__ import annotations

import math

import pytest

from l1flow_rl.workspace.evaluator import SELECTION_RULES, choose_evaluation


def _rows(values, episodes=50, **first):
    rows = [
        {"step": 2000 * i, "split": "val", "success_once": v, "episodes": episodes}
        for i, v in enumerate(values)
    ]
    rows[0].update(first)
    return rows


def _step(values, rule, **first):
    return choose_evaluation(_rows(values, **first), "success_once", rule)["step"]


def test_start_rule_keeps_the_start_on_a_lead_within_its_standard_error():
    # Square's continued-BC curve: the last model led the start by 0.02 on 50 episodes and tested
    # 12 points below it (finetune_online_robosuite_square50_mlp.json)
    curve = [0.54, 0.50, 0.52, 0.46, 0.56]
    assert _step(curve, "earliest") == 8000
    assert _step(curve, "start") == 0
    se = math.sqrt(0.54 * 0.46 / 50)  # 0.0705
    assert _step([0.54, 0.54 + se - 0.001], "start") == 0
    assert _step([0.54, 0.54 + se + 0.001], "start") == 2000


def test_start_rule_takes_the_earliest_best_later_model_once_one_clears_the_margin():
    assert _step([0.34, 0.16, 0.58, 0.46, 0.58], "start") == 4000
    assert _step([0.34, 0.16, 0.58, 0.46, 0.60], "start") == 8000


def test_start_rule_reads_the_recorded_standard_error_first():
    # a start validated on many episodes has a small error: a small lead is then evidence
    assert _step([0.54, 0.56], "start", standard_error=0.01) == 2000
    assert _step([0.54, 0.60], "start", standard_error=0.08) == 0


def test_start_rule_edges():
    assert _step([0.3], "start") == 0  # the start alone
    assert _step([0.0, 0.02], "start") == 2000  # a start that never succeeds has no error to clear
    assert _step([1.0, 1.0], "start") == 0


@pytest.mark.parametrize(("rule", "step"), [("earliest", 2000), ("latest", 4000), ("start", 2000)])
def test_equal_figures_go_to_the_rule_s_end(rule, step):
    assert _step([0.1, 0.9, 0.9], rule) == step


def test_unknown_rule_and_empty_validation_are_refused():
    assert SELECTION_RULES == ("earliest", "latest", "start")
    with pytest.raises(ValueError, match="rule='best'; expected one of"):
        choose_evaluation(_rows([0.5]), "success_once", "best")
    with pytest.raises(ValueError, match="no validation evaluation"):
        choose_evaluation([], "success_once", "start")
