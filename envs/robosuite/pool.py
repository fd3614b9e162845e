"""Worker pools for replaying and scripting robosuite episodes (``concurrent.futures``): forkserver
processes with robosuite preloaded, or this process when one worker is asked for (no start-up cost:
small batches and tests)."""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
from collections.abc import Callable

__all__ = ["InProcessExecutor", "worker_pool"]


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
    from l1flow_rl.envs.robosuite import _forkserver

    ctx = multiprocessing.get_context(_forkserver())
    return cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=initializer, initargs=initargs)
