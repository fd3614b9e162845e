"""A run's cost: CPU seconds include every worker it started, and totals carry across resumes."""

from __future__ import annotations

import multiprocessing
import time

import pytest

from l1flow_rl.workspace.run_clock import RunClock, process_cpu_seconds


def _burn(seconds: float) -> None:
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass


def test_cpu_seconds_count_workers_a_forkserver_started_and_reaped():
    # ParallelEnv starts robosuite/PushT workers through a forkserver: they are its children, not
    # ours, so the process's RUSAGE_CHILDREN never sees them.
    ctx = multiprocessing.get_context("forkserver")
    warm = ctx.Process(target=_burn, args=(0.0,))  # starts the forkserver outside the measurement
    warm.start()
    warm.join()
    before = process_cpu_seconds()
    worker = ctx.Process(target=_burn, args=(0.6,))
    worker.start()
    worker.join()
    assert worker.exitcode == 0
    assert process_cpu_seconds() - before >= 0.5


def test_totals_add_the_checkpointed_ones_and_name_where_counting_began():
    prior = {"train": 100.0, "wall": 150.0, "cpu": 120.0, "since_step": 0}
    clock = RunClock(prior, phases=("train",))
    clock.resumed_at(400)  # totals exist: the figures still cover the whole run
    clock.start("train")
    _burn(0.05)
    clock.stop("train")
    totals = clock.totals()
    assert totals["since_step"] == 0
    assert 100.05 <= totals["train"] < 101.0 and totals["wall"] >= 150.05 and totals["cpu"] > 120.0
    assert clock.summary()["train_seconds"] == pytest.approx(totals["train"], abs=0.051)

    old = RunClock(None, phases=("train",))  # a checkpoint written before totals existed
    old.resumed_at(400)
    assert old.summary()["seconds_since_step"] == 400 and old.summary()["train_seconds"] == 0.0


def test_a_running_phase_counts_up_to_now():
    clock = RunClock(None, phases=("online",))
    clock.start("online")
    time.sleep(0.05)
    assert clock.totals()["online"] >= 0.05  # a checkpoint mid-phase records the time spent so far
