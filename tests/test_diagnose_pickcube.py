"""The PickCube failure diagnosis puts each episode in exactly one phase, from what its states show."""

import pytest

from benchmarks.diagnose_pickcube import GOAL_THRESH, main, phase


def _row(**kw):
    row = {"first_success_step": None, "first_grasp_step": 40, "held_at_end": True, "goal_dist_min": 0.03}
    return {**row, **kw}


@pytest.mark.parametrize(
    ("row", "expected"),
    [
        (_row(first_success_step=70, goal_dist_min=0.01), "success"),
        (_row(first_grasp_step=None, held_at_end=False, goal_dist_min=0.2), "no_grasp"),
        (_row(goal_dist_min=GOAL_THRESH), "placed_not_static"),  # inside the goal, never a success
        (_row(goal_dist_min=0.033), "carried_short"),  # held at the end, parked outside the goal
        (_row(held_at_end=False, goal_dist_min=0.04), "carried_short"),  # let go, but came near
        (_row(held_at_end=False, goal_dist_min=0.12), "dropped"),
    ],
)
def test_each_episode_lands_in_one_phase(row, expected):
    assert phase(row) == expected


def test_a_checkpoint_argument_without_a_name_is_refused_before_anything_loads(capsys):
    with pytest.raises(SystemExit):
        main(["--checkpoints", "runs/x/best.pt", "--out", "unused.json"])
    assert "expected NAME=PATH" in capsys.readouterr().err
