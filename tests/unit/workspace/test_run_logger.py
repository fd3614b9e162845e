"""The run's TorchRL logger across a resume: it logs under the run directory it is resumed in."""

from __future__ import annotations

import shutil

import pytest

from l1flow_rl.workspace.logging import make_logger


@pytest.mark.parametrize("kind", ["csv", "tensorboard"])
def test_a_resumed_logger_writes_under_the_run_dir_it_is_resumed_in(tmp_path, kind):
    """A run copied to another directory (or resumed with another run_dir) logs there, not into the
    directory the saved logger state names; a CSV keeps its earlier rows and appends."""
    if kind == "tensorboard":
        pytest.importorskip("tensorboard", reason="the tensorboard logger needs tensorboard")
    first, copy = tmp_path / "first", tmp_path / "copy"
    logger = make_logger(kind, first, None, default_name="finetune")
    logger.log_scalar("online/success", 0.5, step=1)
    state = logger.state_dict()
    assert str(first) in str(state["log_dir"])
    shutil.copytree(first, copy)
    before = sorted(p.relative_to(first) for p in first.rglob("*") if p.is_file())
    resumed = make_logger(kind, copy, state, default_name="finetune")
    resumed.log_scalar("online/success", 0.75, step=2)
    after = sorted(p.relative_to(first) for p in first.rglob("*") if p.is_file())
    assert after == before  # nothing new in the old directory
    assert str(copy) in str(resumed.log_dir)
    if kind == "csv":
        rows = (copy / "logs" / "finetune" / "scalars" / "online" / "success.csv").read_text().split()
        assert rows == ["1,0.5", "2,0.75"]
        assert (first / "logs" / "finetune" / "scalars" / "online" / "success.csv").read_text().split() == [
            "1,0.5"
        ]
