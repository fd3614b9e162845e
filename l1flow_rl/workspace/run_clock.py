"""What a run has cost, summed over the invocations that resumed it.

A run killed and resumed (``resume=true``) would otherwise report only its last invocation's
seconds; benchmarks read these figures as the run's budget. The totals travel in every checkpoint
(``RunClock.totals()``, saved under ``elapsed``); work done after the last checkpoint of a killed
invocation is lost and not counted.
"""

from __future__ import annotations

import resource
import time
from collections.abc import Mapping, Sequence
from typing import Any

#: what ``cpu_seconds`` covers; summaries without it counted the run's own process and its direct
#: children only, missing simulator workers started through a forkserver.
CPU_SCOPE = "process tree"


def process_cpu_seconds() -> float:
    """User + system CPU time of this process and of every process it started (demo and env workers).

    Finished children come from ``RUSAGE_CHILDREN``; live descendants are read with psutil, each
    with the children it reaped: a forkserver (how ParallelEnv starts robosuite and PushT workers)
    reaps the workers it forks, so ``RUSAGE_CHILDREN`` alone misses their time.
    """
    # optional dependency (app extra): CPU accounting of worker processes
    import psutil

    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    total = own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime
    for proc in psutil.Process().children(recursive=True):
        try:
            t = proc.cpu_times()
        except (psutil.NoSuchProcess, psutil.AccessDenied):  # ended between listing and reading
            continue
        total += t.user + t.system + t.children_user + t.children_system
    return total


class RunClock:
    """Seconds per named phase, in all (``wall``) and on the CPU (``cpu``), across resumes.

    ``prior`` is the ``elapsed`` record of the checkpoint being continued (None: a fresh run, or a
    checkpoint written before the totals existed; then call :meth:`resumed_at`, so that
    ``since_step`` names the step from which the figures count; 0: the whole run).

    >>> clock = RunClock(None, phases=("train",))
    >>> clock.start("train"); clock.stop("train")
    >>> sorted(clock.totals())
    ['cpu', 'since_step', 'train', 'wall']
    """

    def __init__(self, prior: Mapping[str, Any] | None, phases: Sequence[str]) -> None:
        self._start = time.perf_counter()
        self._keys = (*phases, "wall", "cpu")
        self._own = dict.fromkeys(phases, 0.0)
        self._open: dict[str, float] = {}
        self._prior = {k: float((prior or {}).get(k, 0.0)) for k in self._keys}
        self._has_prior = prior is not None
        self.since_step = int(prior.get("since_step", 0)) if prior else 0

    def resumed_at(self, step: int) -> None:
        """The run continues from ``step``; without earlier totals its figures count from there."""
        if not self._has_prior:
            self.since_step = int(step)

    def start(self, phase: str) -> None:
        self._open[phase] = time.perf_counter()

    def stop(self, phase: str) -> None:
        self._own[phase] += time.perf_counter() - self._open.pop(phase)

    def totals(self) -> dict[str, float]:
        """The run's seconds so far, earlier invocations included (a running phase counts to now)."""
        now = time.perf_counter()
        own = {p: s + (now - self._open[p] if p in self._open else 0.0) for p, s in self._own.items()}
        # CPU counts from the process start: every invocation's imports and start-up are part of the cost.
        own.update(wall=now - self._start, cpu=process_cpu_seconds())
        return {**{k: self._prior[k] + own[k] for k in self._keys}, "since_step": self.since_step}

    def summary(self) -> dict[str, float]:
        """``<phase>_seconds`` for every phase (and wall, cpu), rounded; ``seconds_since_step``; and
        ``cpu_seconds_scope``, what the CPU figure covers."""
        totals = self.totals()
        return {
            **{f"{k}_seconds": round(totals[k], 1) for k in self._keys},
            "seconds_since_step": totals["since_step"],
            "cpu_seconds_scope": CPU_SCOPE,
        }
