"""Worker pools for replaying and scripting robosuite episodes (``concurrent.futures``): forkserver
processes with robosuite preloaded, or this process when one worker is asked for (no start-up cost:
small batches and tests)."""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
from collections.abc import Callable

from l1flow_rl.envs.robosuite.sim import choose_gl
from l1flow_rl.envs.workers import restore_stop_signals, simulator_forkserver

__all__ = ["InProcessExecutor", "forkserver", "worker_pool"]

#: imported once by the forkserver, so each worker forks with robosuite already imported (~3 s each)
_WORKER_PRELOAD = ["torch", "torchrl.envs", "robosuite", "l1flow_rl.envs.robosuite.env"]


def forkserver() -> str:
    """The start method of robosuite's worker processes: a forkserver with robosuite preloaded."""
    os.environ.setdefault("MUJOCO_GL", choose_gl())  # the server reads it when it imports robosuite
    return simulator_forkserver(_WORKER_PRELOAD)


class InProcessExecutor(cf.Executor):
    """An executor that runs each call at submission, in this process."""

    def submit(self, fn, /, *args, **kwargs) -> cf.Future:
        future: cf.Future = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as err:  # handed to the caller through the future, as a pool would
            future.set_exception(err)
        return future


def worker_pool(workers: int, initializer: Callable[..., None], initargs: tuple = ()) -> cf.Executor:
    """``workers`` processes that each ran ``initializer(*initargs)`` (1: this process)."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if workers == 1:
        initializer(*initargs)
        return InProcessExecutor()
    ctx = multiprocessing.get_context(forkserver())
    return cf.ProcessPoolExecutor(
        workers, mp_context=ctx, initializer=_pool_worker, initargs=(initializer, *initargs)
    )


def _pool_worker(initializer: Callable[..., None], *initargs) -> None:
    restore_stop_signals()  # the forkserver ignores them; the demos' main process does not handle them
    initializer(*initargs)
