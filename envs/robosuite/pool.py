"""Worker pools for replaying and scripting robosuite episodes (``concurrent.futures``): forkserver
processes with robosuite preloaded, or this process when one worker is asked for (no start-up cost:
small batches and tests)."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing
import os
import signal
import threading
from collections.abc import Callable, Iterator

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
    pool = cf.ProcessPoolExecutor(
        workers, mp_context=ctx, initializer=_pool_worker, initargs=(initializer, *initargs)
    )
    # Start every worker now, with Ctrl-C deferred: a Ctrl-C inside a worker's start (the first
    # waits for the forkserver to import robosuite) left that worker unknown to the pool, and it
    # failed with a FileNotFoundError traceback on the pool's semaphores once this process had gone.
    # Each of the first ``workers`` submissions finds no idle worker, so it starts one.
    try:
        with _sigint_deferred():
            for _ in range(workers):
                pool.submit(_ready)
    except BaseException:
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    return pool


@contextlib.contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Ctrl-C inside the block is held, not lost: its KeyboardInterrupt comes when the block ends.

    Two parts, both needed. SIGINT is blocked in this thread, a mask that the forkserver this block
    may start inherits (a handler is not): a Ctrl-C while the server imported robosuite killed it,
    and the pool failed with EOFError. And a handler only records it, because the kernel may
    deliver it to another thread (tqdm's monitor), from where Python would still interrupt this one
    mid-``submit``."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers belong to the main thread
        return
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a held Ctrl-C is recorded here
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


def _ready() -> None:
    """A worker's first call: nothing, its start is the point."""


def _pool_worker(initializer: Callable[..., None], *initargs) -> None:
    restore_stop_signals()  # the forkserver ignores them; the demos' main process does not handle them
    initializer(*initargs)
