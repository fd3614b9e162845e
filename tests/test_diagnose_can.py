"""The Can failure diagnosis puts each episode in exactly one phase, from what its states show."""

import pytest

from benchmarks.diagnose_can import main, phase


def _row(**kw):
    row = {"first_success_step": None, "first_lift_step": 60, "first_over_bin_step": None}
    return {**row, "held_at_end": True, **kw}


@pytest.mark.parametrize(
    ("row", "expected"),
    [
        (_row(first_success_step=150, first_over_bin_step=120, held_at_end=False), "success"),
        (_row(first_lift_step=None, held_at_end=False), "no_lift"),
        (_row(first_over_bin_step=130), "over_bin_not_placed"),  # held over the bin at the limit
        (_row(first_over_bin_step=130, held_at_end=False), "over_bin_not_placed"),  # let go, not in
        (_row(), "carried_not_over_bin"),
        (_row(held_at_end=False), "dropped"),
    ],
)
def test_each_episode_lands_in_one_phase(row, expected):
    assert phase(row) == expected


def test_a_checkpoint_argument_without_a_path_is_refused_before_anything_loads(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--checkpoints", "start", "--out", str(tmp_path / "unused.json")])
    assert "expected NAME=PATH" in capsys.readouterr().err


def test_the_report_tabulates_each_policys_phases_on_the_same_columns():
    from benchmarks.finetune_report import render_failure_phases

    data = {
        "episode_seeds": {"first": 100000, "episodes": 3},
        "policies": {
            "start": {"checkpoint": "a.pt", "phases": {"no_lift": 2, "success": 1}},
            "tuned": {"checkpoint": "b.pt", "phases": {"success": 2, "dropped": 1}},
        },
    }
    text = render_failure_phases(data)
    assert "| policy | checkpoint | success | dropped | no_lift |" in text
    assert "| start | `a.pt` | 1 | 0 | 2 |" in text  # a phase a policy never reached reads 0
    assert "| tuned | `b.pt` | 2 | 1 | 0 |" in text
