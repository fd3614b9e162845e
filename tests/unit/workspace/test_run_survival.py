"""Runs that survive the cluster, on the real ``l1flow-rl train`` in processes of its own (the
point-mass double): a pre-emption signal checkpoints and resumes bit-exactly, a diverging run stops
naming the step with its last checkpoint finite, and a busy run directory refuses a second process."""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from doubles.point_mass import TASK_OVERRIDES

from l1flow_rl.commands.cli import main
from l1flow_rl.workspace.checkpoint import first_non_finite, load_checkpoint

TESTS = Path(__file__).parents[2]
STEPS = 150


def _args(data_dir, run_dir, *extra) -> list[str]:
    return [
        "train",
        *TASK_OVERRIDES,
        "demos.num=4",
        f"train.steps={STEPS}",
        "train.batch_size=16",
        "train.warmup_steps=2",
        "train.log_every=1",
        "train.checkpoint_every=20",
        "eval.enabled=false",
        "network.down_dims=[16,32]",
        "device=cpu",
        f"data_dir={data_dir}",
        f"run_dir={run_dir}",
        *extra,
    ]


def _start(args: list[str], log: Path) -> subprocess.Popen:
    """``l1flow-rl ARGS`` with the double registered, its stderr (progress bar, messages) in ``log``."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    env["OMP_NUM_THREADS"] = "1"
    with open(log, "w") as err:
        return subprocess.Popen(
            [sys.executable, "-m", "doubles.cli", *args], stdout=subprocess.DEVNULL, stderr=err, env=env
        )


def _wait_for_step(
    proc: subprocess.Popen, log: Path, step: int, timeout: float = 120, total: str = r"\d+"
) -> None:
    """Until the progress bar in ``log`` shows at least ``step`` of ``total`` steps done."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        done = [int(n) for n in re.findall(rf"(\d+)/{total} ", log.read_text())]
        if done and max(done) >= step:
            return
        assert proc.poll() is None, f"the run ended early:\n{log.read_text()[-2000:]}"
        time.sleep(0.05)
    raise AssertionError(f"step {step} not reached in {timeout} s:\n{log.read_text()[-2000:]}")


def _stopped_at(text: str, job: str = "train") -> int:
    found = re.search(
        rf"^l1flow-rl {job}: stopped by SIGTERM at step (\d+); checkpoint \S+ holds it", text, re.M
    )
    assert found, text[-2000:]
    return int(found.group(1))


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("demos")


@pytest.fixture(scope="module")
def straight(tmp_path_factory, data_dir):
    """The uninterrupted run (in this process; it also makes the demonstrations once)."""
    run_dir = tmp_path_factory.mktemp("straight") / "run"
    assert main(_args(data_dir, run_dir)) == 0
    # eval.enabled=false: no validation and no test, so latest.pt alone and no eval.json
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == ["latest.pt"]
    assert (run_dir / "summary.json").is_file() and not (run_dir / "eval.json").exists()
    return load_checkpoint(run_dir / "checkpoints" / "latest.pt")


def test_sigterm_checkpoints_and_the_printed_resume_command_ends_where_an_uninterrupted_run_ends(
    tmp_path, data_dir, straight
):
    run_dir, log = tmp_path / "run", tmp_path / "stderr.txt"
    proc = _start(_args(data_dir, run_dir), log)
    _wait_for_step(proc, log, 30)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=120) == 128 + signal.SIGTERM
    text = log.read_text()
    step = _stopped_at(text)
    assert 30 <= step < STEPS
    assert "Traceback" not in text
    assert load_checkpoint(run_dir / "checkpoints" / "latest.pt")["step"] == step  # not the step-20 one

    # The exact command the message gives, run as printed.
    command = shlex.split(re.search(r"Resume with: (.*)$", text, re.M).group(1))
    assert command[:2] == ["l1flow-rl", "train"] and command[-2:] == ["resume=true", f"run_dir={run_dir}"]
    resumed_log = tmp_path / "resumed.txt"
    assert _start(command[1:], resumed_log).wait(timeout=300) == 0, resumed_log.read_text()[-2000:]
    resumed = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert resumed["step"] == straight["step"] == STEPS
    for part in ("model", "ema"):
        assert [k for k in straight[part] if not torch.equal(straight[part][k], resumed[part][k])] == [], part
    assert resumed["history"] == straight["history"]


def test_a_diverging_run_stops_naming_the_step_and_its_last_checkpoint_is_finite(tmp_path, data_dir, capsys):
    # lr 30 takes the double's loss to NaN after about 15 steps (lr 1e8 does within 3, before any
    # checkpoint); metrics are read, and checkpoints written, every 5 steps. (No validation: the
    # double's physics turn the actions of weights that large into NaN observations. That a NaN
    # never reaches best.pt is tests/unit/workspace/test_harness.py's.)
    run_dir = tmp_path / "run"
    assert main(_args(data_dir, run_dir, "train.lr=30", "train.log_every=5", "train.checkpoint_every=5")) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("l1flow-rl")]
    assert len(lines) == 1 and "Traceback" not in err, err
    found = re.match(r"l1flow-rl train: train diverged: at step (\d+) loss_l1flow=nan", lines[0])
    assert found, lines[0]
    step = int(found.group(1))
    assert step % 5 == 0 and 5 < step < STEPS
    latest = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert latest["step"] == step - 5 and first_non_finite(latest) is None
    assert f"{run_dir / 'checkpoints' / 'latest.pt'}, is from step {step - 5} and finite" in lines[0]


def test_a_busy_run_directory_refuses_a_second_process_and_a_killed_ones_lock_does_not_block(
    tmp_path, data_dir, straight
):
    run_dir = tmp_path / "run"
    first = _start(_args(data_dir, run_dir, "train.steps=100000"), tmp_path / "first.txt")
    try:
        _wait_for_step(first, tmp_path / "first.txt", 20, timeout=120)  # its checkpoint at step 20
        second = subprocess.run(
            [
                sys.executable,
                "-m",
                "doubles.cli",
                *_args(data_dir, run_dir, "train.steps=100000", "resume=true"),
            ],
            capture_output=True,
            text=True,
            env={**os.environ, "PYTHONPATH": str(TESTS), "OMP_NUM_THREADS": "1"},
            timeout=120,
        )
        assert second.returncode == 2
        assert second.stderr.strip().splitlines() == [
            f"l1flow-rl train: run_dir {str(run_dir)!r} is in use by process {first.pid} (it holds "
            f"{run_dir / '.lock'}); wait for that run to end, or choose another run_dir"
        ]
        assert first.poll() is None  # the first run goes on
    finally:
        first.kill()  # SIGKILL: no clean-up, the lock file stays behind
        first.wait()
    assert (run_dir / ".lock").read_text().strip() == str(first.pid)
    saved = load_checkpoint(run_dir / "checkpoints" / "latest.pt")["step"]

    # The killed run's lock does not block its resume: it trains on (then is stopped by SIGTERM).
    log = tmp_path / "third.txt"
    third = _start(_args(data_dir, run_dir, "train.steps=100000", "resume=true"), log)
    _wait_for_step(third, log, saved + 5)
    third.send_signal(signal.SIGTERM)
    assert third.wait(timeout=120) == 128 + signal.SIGTERM
    assert _stopped_at(log.read_text()) >= saved + 5


ONLINE_STEPS = 600
#: filtered BC online on the double: 60 warm-up env steps, then rounds of 60 (2 envs), 0.5 updates per
#: env step, a checkpoint every 120 env steps
FINETUNE = [
    *TASK_OVERRIDES,
    "finetune=filtered_bc",
    "offline.steps=0",
    f"online.steps={ONLINE_STEPS}",
    "online.warmup_steps=60",
    "online.num_envs=2",
    "online.frames_per_round=60",
    "online.updates_per_step=0.5",
    "online.checkpoint_every=120",
    "finetune.batch_size=16",
    "eval.enabled=false",
    "device=cpu",
]


# ~40 s, slow; by default a SIGTERM'd training run resumes exactly (above) and so does an online
# fine-tune stopped mid-way (test_finetune_job)
@pytest.mark.slow
def test_sigterm_during_online_fine_tuning_checkpoints_and_resumes_bit_exactly(tmp_path, data_dir):
    # the online buffer's TorchRL storage installs its own SIGTERM handler (it deletes the buffer's
    # files, then passes the signal on to ours), ahead of the harness's: the run must still finish
    # the step, write its buffer into the checkpoint, and resume to the uninterrupted run's end
    bc = tmp_path / "bc"
    assert main(_args(data_dir, bc, "train.steps=30")) == 0
    start = f"checkpoint={bc / 'checkpoints' / 'latest.pt'}"
    straight_dir, run_dir, log = tmp_path / "straight", tmp_path / "run", tmp_path / "stderr.txt"
    assert main(["finetune", start, f"data_dir={data_dir}", f"run_dir={straight_dir}", *FINETUNE]) == 0

    proc = _start(["finetune", start, f"data_dir={data_dir}", f"run_dir={run_dir}", *FINETUNE], log)
    _wait_for_step(proc, log, 250, total=str(ONLINE_STEPS))  # online, past the 240-step checkpoint
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=120) == 128 + signal.SIGTERM
    text = log.read_text()
    assert "Traceback" not in text
    step = _stopped_at(text, "finetune")
    assert 250 <= step < ONLINE_STEPS
    assert load_checkpoint(run_dir / "checkpoints" / "latest.pt")["progress"]["env_steps"] == step

    command = shlex.split(re.search(r"Resume with: (.*)$", text, re.M).group(1))
    resumed_log = tmp_path / "resumed.txt"
    assert _start(command[1:], resumed_log).wait(timeout=300) == 0, resumed_log.read_text()[-2000:]
    straight = load_checkpoint(straight_dir / "checkpoints" / "latest.pt")
    resumed = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert resumed["progress"] == straight["progress"] and straight["progress"]["env_steps"] == ONLINE_STEPS
    model = straight["model"]
    assert [k for k in model if not torch.equal(model[k], resumed["model"][k])] == []
    # filtered BC has no critic: its critic columns hold NaN, which equals nothing, so compare as JSON
    assert json.dumps(resumed["history"], sort_keys=True) == json.dumps(straight["history"], sort_keys=True)
