"""A run's success plot draws validation and the test of the shipped weights with its interval, at
the step of those weights, including a test at zero successes (its interval starts at the point)."""

from l1flow_rl.evaluation import wilson_interval
from l1flow_rl.workspace.report import save_plots


def test_the_success_plot_draws_a_test_at_zero_successes_and_at_every_success(tmp_path):
    val = [
        {"step": s, "split": "val", "success_once": 0.5, "success_at_end": 0.0, "episodes": 20}
        for s in (5, 10)
    ]
    test = {"step": 10, "weights_step": 5, "split": "test", "episodes": 50}
    test.update(success_once=1.0, success_at_end=0.0)
    test["ci95"] = {"success_once": wilson_interval(50, 50), "success_at_end": wilson_interval(0, 50)}
    written = save_plots({"step": [1, 2], "loss": [1.0, 0.5], "lr": [1e-4, 1e-4]}, [*val, test], tmp_path)
    assert written == [tmp_path / "loss.png", tmp_path / "success.png"]
    assert (tmp_path / "success.png").stat().st_size > 0
