"""Simulator workers start inside joblib's loky workers (hydra's joblib launcher runs each job in
one): there the process-wide start method is ``"loky"``, which every forkserver- or spawn-started
child would try to set again and fail on (``ValueError: cannot find context for 'loky'``)."""

import multiprocessing
import os

import pytest
from l1flow_rl.envs.workers import simulator_forkserver


def _start_workers(prepare: bool) -> tuple[str | None, list[int | None]]:
    """In a loky worker: (its start method, the exit codes of a forkserver and a spawn child)."""
    seen = multiprocessing.get_start_method(allow_none=True)
    method = simulator_forkserver([]) if prepare else "forkserver"
    codes = []
    for name in (method, "spawn"):
        child = multiprocessing.get_context(name).Process(target=os.getpid)
        child.start()
        child.join(timeout=60)
        codes.append(child.exitcode)
    return seen, codes


def test_workers_start_inside_a_loky_worker():
    joblib = pytest.importorskip("joblib")
    parallel = joblib.Parallel(n_jobs=2, backend="loky")
    # without simulator_forkserver's reset the children die while starting: what the fix is for
    seen, codes = parallel([joblib.delayed(_start_workers)(False)])[0]
    assert seen == "loky" and codes == [1, 1]
    assert parallel([joblib.delayed(_start_workers)(True)])[0][1] == [0, 0]
