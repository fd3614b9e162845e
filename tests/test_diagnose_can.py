"""The Can failure diagnosis puts each episode in exactly one phase, from what its states show."""

import numpy as np
import pytest

from benchmarks.diagnose_can import first_close, main, phase


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


def test_the_first_grasp_is_where_the_fingers_first_close_by_5mm_with_the_hand_offset_there():
    states = np.zeros((6, 23))
    states[:, 7:10] = [0.1, -0.4, 0.86]  # the can
    states[:, 14:17] = [
        [0.0, -0.1, 1.0],
        [0.05, -0.2, 0.95],
        [0.08, -0.3, 0.9],
        [0.09, -0.36, 0.87],
        [0.09, -0.36, 0.87],
        [0.09, -0.36, 0.87],
    ]
    # finger joints (+, -): open 4 cm each, closing by 2 mm (noise, not a grasp), then by 1 cm at step 3
    states[:, 21] = [0.04, 0.04, 0.039, 0.035, 0.03, 0.03]
    states[:, 22] = [-0.04, -0.04, -0.04, -0.035, -0.03, -0.03]
    step, offset = first_close(states)
    assert step == 3 and offset == [-0.01, 0.04]  # 1 cm short in x, 4 cm on the start side in y
    states[:, 21], states[:, 22] = 0.04, -0.04
    assert first_close(states) == (None, None)  # never closed


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
