"""Errors a user can fix read as one line from the real command: ``l1flow-rl <command>: <what is
wrong and what to do>`` on stderr, exit code 2, no traceback; ``--debug`` keeps the traceback."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from doubles.point_mass import TASK_OVERRIDES

from l1flow_rl.commands.cli import main
from l1flow_rl.errors import CheckpointReadError

TESTS = Path(__file__).parents[2]


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(TESTS), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "doubles.cli", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=cwd,
        timeout=120,
    )


def _one_line(proc: subprocess.CompletedProcess, command: str) -> str:
    assert proc.returncode == 2, proc.stderr[-3000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert lines[0].startswith(f"l1flow-rl {command}: ")
    return lines[0]


class _Payload:
    """Stands for any object a foreign pickle might hold."""


def test_a_missing_data_file_is_one_line_naming_it(tmp_path):
    missing = tmp_path / "nowhere" / "demos.hdf5"
    proc = _cli(
        "train",
        *TASK_OVERRIDES,
        f"data.path={missing}",
        "device=cpu",
        f"run_dir={tmp_path / 'run'}",
        cwd=tmp_path,
    )
    assert str(missing) in _one_line(proc, "train")


def test_a_corrupt_checkpoint_is_one_line_naming_it_without_torchs_advice(tmp_path):
    good = tmp_path / "good.pt"
    torch.save({"model": {"w": torch.zeros(10_000)}, "config": {}}, good)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:5000])
    line = _one_line(
        _cli("eval", f"checkpoint={truncated}", f"run_dir={tmp_path / 'ev'}", cwd=tmp_path), "eval"
    )
    assert str(truncated) in line and "truncated" in line

    # Files holding other objects (torch's format, or a bare pickle): refused in words of ours,
    # naming the object where torch names it; torch's advice (weights_only=False) never shows.
    saved, bare = tmp_path / "foreign.pt", tmp_path / "bare.pkl"
    torch.save({"model": _Payload(), "config": {}}, saved)
    with open(bare, "wb") as f:
        pickle.dump({"model": _Payload(), "config": {}}, f)
    for path, named in ((saved, "_Payload"), (bare, "")):
        with pytest.raises(CheckpointReadError) as info:
            main(["--debug", "eval", f"checkpoint={path}", f"run_dir={tmp_path / 'ev2'}"])
        assert str(path) in str(info.value) and named in str(info.value)
        assert info.value.__cause__ is None and info.value.__suppress_context__  # no chained torch message
        assert "weights_only" not in str(info.value)


def test_a_truncated_checkpoint_to_resume_is_one_line_and_debug_shows_the_traceback(tmp_path, capsys):
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "latest.pt").write_bytes(b"PK\x03\x04 torn by a full disk")
    args = ["train", *TASK_OVERRIDES, "device=cpu", f"run_dir={run_dir}", "resume=true"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [err.strip()] and "latest.pt" in err and "truncated" in err, err
    with pytest.raises(CheckpointReadError):
        main(["--debug", *args])


@pytest.mark.parametrize(
    ("override", "named"),
    [
        ("train.stepz=3", "train.stepz"),
        ("task=no_such_task", "task/no_such_task"),
        ("network.down_dims=12", "network.down_dims"),
        ("policy.down_dims=[32,64,128]", "moved to network.down_dims"),
    ],
)
def test_a_bad_override_is_one_line_naming_the_key(override, named, capsys):
    assert main(["train", override]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("l1flow-rl train: invalid config: ") and named in err, err
