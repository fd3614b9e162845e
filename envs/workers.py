"""Worker processes for simulators: the ``if __name__ == "__main__":`` guard they need, checked
before any worker starts, and the stop signals they leave to the main process.

A worker started by forkserver or spawn re-imports the main script (as ``__mp_main__``). Code at
the script's top level that makes worker envs then runs again inside each worker, which fails while
it is still starting, and the parent only sees a dead pipe (``EOFError``, ``ConnectionResetError``,
``BrokenPipeError``). Python's own hint ends up in the worker's traceback, not in the error the user
gets. :func:`check_main_guard` reads the main script instead and names the line that needs the
guard. Hand-written: neither multiprocessing, gymnasium nor TorchRL checks this up front.
"""

from __future__ import annotations

import ast
import atexit
import functools
import multiprocessing
import signal
import sys
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from types import FrameType

import torch
from torchrl.envs import ParallelEnv, SerialEnv

__all__ = [
    "WORKER_IGNORED_SIGNALS",
    "MainGuardError",
    "ParallelWorkerEnv",
    "SerialWorkerEnv",
    "check_main_guard",
    "explain_worker_start_failure",
    "ignore_stop_signals",
    "restore_stop_signals",
    "signal_safe_factory",
    "simulator_forkserver",
    "standard_start_method",
]

#: what a simulator worker ignores: the run's stop signals (SIGTERM, SIGUSR1) and Ctrl-C's SIGINT
WORKER_IGNORED_SIGNALS = (signal.SIGTERM, signal.SIGUSR1, signal.SIGINT)

_GUARD_HINT = (
    'put the code that makes the env under `if __name__ == "__main__":` (worker processes re-import '
    "the main script; see the 'safe importing of main module' note in Python's multiprocessing docs)"
)


class MainGuardError(RuntimeError):
    """A script makes worker envs at import time, without the ``__main__`` guard."""


def _is_main_guard(test: ast.expr) -> bool:
    """``__name__ == "__main__"`` (either order), alone or inside an ``and``."""
    if isinstance(test, ast.BoolOp) and isinstance(test.op, ast.And):
        return any(_is_main_guard(value) for value in test.values)
    if not (isinstance(test, ast.Compare) and len(test.ops) == 1 and isinstance(test.ops[0], ast.Eq)):
        return False
    sides = [test.left, test.comparators[0]]
    names = [s for s in sides if isinstance(s, ast.Name) and s.id == "__name__"]
    mains = [s for s in sides if isinstance(s, ast.Constant) and s.value == "__main__"]
    return len(names) == 1 and len(mains) == 1


def _guarded(tree: ast.Module, line: int) -> bool:
    """Whether ``line`` (of a top-level statement) lies in the body of a ``__main__`` guard."""
    stack: list[ast.AST] = list(tree.body)
    while stack:
        node = stack.pop()
        start, end = getattr(node, "lineno", None), getattr(node, "end_lineno", None)
        if start is None or end is None or not start <= line <= end:
            continue
        if isinstance(node, ast.If) and _is_main_guard(node.test):
            in_body = any(s.lineno <= line <= (s.end_lineno or s.lineno) for s in node.body)
            if in_body:
                return True
        stack.extend(ast.iter_child_nodes(node))
    return False


def _main_script_frame(frame: FrameType | None) -> tuple[Path, FrameType] | None:
    """The frame running the main script's top-level code, if this call comes from there."""
    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if not path:  # interactive, ``python -c``, a notebook: nothing is re-imported
        return None
    script = Path(path).resolve()
    found = None
    while frame is not None:
        code = frame.f_code
        if code.co_name == "<module>" and frame.f_globals.get("__name__") == "__main__":
            try:
                if Path(code.co_filename).resolve() == script:
                    found = frame
            except OSError:
                pass
        frame = frame.f_back
    return (script, found) if found is not None else None


def check_main_guard(what: str) -> None:
    """Raise :class:`MainGuardError` when the caller runs at the top level of the main script
    outside an ``if __name__ == "__main__":`` guard, where a worker's re-import would run it again.

    ``what`` names what needs the workers, for the message (e.g. ``"ManiSkill on the CPU with
    num_envs=2"``). Silent when the main
    script cannot be read, or the call comes from a guard, a function the guard calls, an
    interactive session, ``python -c`` or a notebook.
    """
    found = _main_script_frame(sys._getframe(1))
    if found is None:
        return
    script, frame = found
    try:
        tree = ast.parse(script.read_text(), filename=str(script))
    except (OSError, SyntaxError, ValueError):
        return
    line = frame.f_lineno
    if not _guarded(tree, line):
        raise MainGuardError(
            f"{what} needs worker processes, but {script} makes them at import time (line {line}, "
            f'outside `if __name__ == "__main__":`), so every worker would start workers of its own; '
            f"{_GUARD_HINT}"
        )


@contextmanager
def explain_worker_start_failure(what: str):
    """Turn a worker that died while starting (a broken pipe in this process) into an error that
    says so, instead of a bare ``EOFError``/``ConnectionResetError``; the worker's own traceback
    is printed above it."""
    try:
        yield
    except (EOFError, ConnectionError) as err:  # ConnectionError covers BrokenPipe/ConnectionReset
        raise RuntimeError(
            f"{what}: a worker process exited while starting ({type(err).__name__}: {err}); its own "
            f"traceback is printed above. If it ran the script that made it again, {_GUARD_HINT}"
        ) from err


def ignore_stop_signals() -> None:
    """Ignore :data:`WORKER_IGNORED_SIGNALS` in this process (and the processes it forks)."""
    for sig in WORKER_IGNORED_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)


def restore_stop_signals() -> None:
    """Undo :func:`ignore_stop_signals` (what a forkserver's children inherit) for SIGTERM and SIGUSR1:
    for pool workers, whose main process does not handle those, so that a group's signal ends them
    with it. Ctrl-C stays ignored: the main process reports it once and shuts its pool down, instead
    of every worker printing a KeyboardInterrupt traceback."""
    for sig in WORKER_IGNORED_SIGNALS:
        if sig != signal.SIGINT:
            signal.signal(sig, signal.SIG_DFL)


@functools.cache
def _kill_daemonic_workers_at_exit() -> None:
    """Register (once, in the main process) the exit step that multiprocessing's own cannot do here.

    At interpreter exit multiprocessing sends SIGTERM to the daemonic children still running (an env
    never closed, or one kept alive by a reference until then), then joins them. Simulator workers
    ignore SIGTERM (:func:`signal_safe_factory`), so that join waited forever (seen: a finished
    ``l1flow-rl train`` hung at exit after writing eval.json).
    atexit runs handlers last-registered first, so this one kills them before multiprocessing's runs.
    """

    def kill_daemonic_children() -> None:
        for child in multiprocessing.active_children():
            if child.daemon:
                child.kill()
                child.join(timeout=10)

    atexit.register(kill_daemonic_children)


def _make_signal_safe(make: Callable, *args, **kwargs):
    # TorchRL also calls the factory in the main process (for the env's specs): ignoring the
    # signals there left a run deaf to Ctrl-C and to its stop signals (seen: a parallel PushT
    # env turned the main process's SIGINT, SIGTERM and SIGUSR1 handlers into SIG_IGN)
    if multiprocessing.parent_process() is not None:
        ignore_stop_signals()
    return make(*args, **kwargs)


def standard_start_method() -> None:
    """Drop a process-wide start method that multiprocessing itself does not know, before this process
    starts workers of its own.

    joblib's loky workers (hydra's ``joblib`` launcher runs each job in one) set ``"loky"`` as the
    process-wide start method. Every worker started from there, by forkserver or spawn, runs
    ``multiprocessing.spawn.prepare``, which sets that name again in the worker and fails with
    ``ValueError: cannot find context for 'loky'`` before the simulator starts. Reset, the default is
    chosen again on first use (``fork`` on Linux), a name every child knows; the workers still start
    by the method their own context names. Hand-written: neither joblib nor multiprocessing does it.
    """
    method = multiprocessing.get_start_method(allow_none=True)
    if method is not None and method not in multiprocessing.get_all_start_methods():
        multiprocessing.set_start_method(None, force=True)


def signal_safe_factory(make: Callable) -> Callable:
    """``make`` (a worker's env factory) run after :func:`ignore_stop_signals` in a worker process
    (the main process keeps its handlers), for workers that do not come from
    :func:`simulator_forkserver` (whose children inherit it); picklable whenever ``make`` is.

    ``timeout``, SLURM, ``docker stop`` and Ctrl-C signal the whole process group. A worker (or the
    forkserver that forked it: multiprocessing then reports its live workers as exited with code
    255) killed by that signal leaves the main process mid-step, and its checkpoint-and-stop fails on
    a dead worker (seen: a run stopped in validation crashed without its checkpoint; one stopped
    while collecting saved it, then exited with a traceback from closing its workers). Ignoring them
    in the workers lets the main process checkpoint and close them itself; a worker whose main
    process is killed outright still exits when its pipe closes.
    """
    _kill_daemonic_workers_at_exit()
    standard_start_method()
    return functools.partial(_make_signal_safe, make)


def simulator_forkserver(preload: list[str]) -> str:
    """The ``"forkserver"`` start method, its server importing ``preload`` once (each worker then
    forks with the simulator already imported) after :mod:`l1flow_rl.envs.forkserver_signals`, so
    that the server and every worker it forks leave the stop signals to the main process (why:
    :func:`signal_safe_factory`)."""
    multiprocessing.set_forkserver_preload(["l1flow_rl.envs.forkserver_signals", *preload])
    _kill_daemonic_workers_at_exit()
    standard_start_method()
    return "forkserver"


class _ClosesQuietlyUnstarted:
    """``close()`` on a batched env whose workers never started does nothing: TorchRL counts such an
    env as closed and raises "trying to close a closed environment". Once started, TorchRL's rules."""

    def _start_workers(self) -> None:
        self.__dict__["_workers_started_once"] = True  # EnvBase routes some attributes to its specs
        super()._start_workers()

    def close(self, *, raise_if_closed: bool = True) -> None:
        started = self.__dict__.get("_workers_started_once", False)
        super().close(raise_if_closed=raise_if_closed and started)


class ParallelWorkerEnv(_ClosesQuietlyUnstarted, ParallelEnv):
    """TorchRL's ``ParallelEnv``, closable before its first reset, that leaves this process's torch
    threads as they were.

    TorchRL lowers the main process to ``threads - workers`` (so one thread on two cores with two
    workers), sized for a learner that updates while the workers step. Our loops act and update in
    turn, so the update keeps the threads the user set. An explicit ``num_threads`` still wins.
    """

    def _start_workers(self) -> None:
        if self.num_threads is None:
            self.num_threads = torch.get_num_threads()
        super()._start_workers()


class SerialWorkerEnv(_ClosesQuietlyUnstarted, SerialEnv):
    """TorchRL's ``SerialEnv``, closable before its first reset."""
