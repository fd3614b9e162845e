"""What a training run has cost, summed over the invocations that resumed it.

A run killed and resumed (``resume=true``) would otherwise report only its last invocation's
seconds; benchmarks read these figures as the run's budget. The totals travel in every checkpoint
under ``elapsed``; work done after the last checkpoint of a killed invocation is lost and not counted.
"""

from __future__ import annotations

import resource
import time
from typing import Any

PHASES = ("demo", "train", "wall", "cpu")


def process_cpu_seconds() -> float:
    """User + system CPU time of this process and its finished children (demo and env workers)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


class RunClock:
    """Seconds spent making demonstrations, training, in all (wall) and on the CPU, across resumes.

    ``resume_state`` is the checkpoint being continued (None: a fresh run). A checkpoint written
    before totals were recorded leaves the earlier invocations uncounted: ``since_step`` then names
    the step from which the figures count (0: the whole run).
    """

    def __init__(self, resume_state: dict[str, Any] | None) -> None:
        self._start = time.perf_counter()
        self._train_start: float | None = None
        self._train_end: float | None = None
        self._demo = 0.0
        prior = (resume_state or {}).get("elapsed")
        self.prior = {k: float(prior.get(k, 0.0)) for k in PHASES} if prior else dict.fromkeys(PHASES, 0.0)
        if prior:
            self.since_step = int(prior.get("since_step", 0))
        else:  # fresh (0), or resumed from a checkpoint that predates the totals
            self.since_step = int((resume_state or {}).get("step", 0))

    def demos_done(self) -> None:
        self._demo = time.perf_counter() - self._start

    def training_starts(self) -> None:
        self._train_start = time.perf_counter()

    def training_ends(self) -> None:
        self._train_end = time.perf_counter()

    def totals(self) -> dict[str, float]:
        """The run's seconds so far (earlier invocations included); ``since_step`` rides along."""
        now = time.perf_counter()
        train = 0.0
        if self._train_start is not None:
            train = (self._train_end or now) - self._train_start
        # CPU counts from the process start: every invocation's imports and start-up are part of the cost.
        own = {"demo": self._demo, "train": train, "wall": now - self._start, "cpu": process_cpu_seconds()}
        return {**{k: self.prior[k] + own[k] for k in PHASES}, "since_step": self.since_step}
