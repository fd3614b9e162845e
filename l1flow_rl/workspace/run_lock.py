"""One process per run directory: an exclusive lock on ``RUN/.lock``, a file that holds the pid.

The lock is ``fcntl.flock``: the kernel releases it when the process ends, however it ends, so a
lock file left by a killed run never blocks its resume (a pid file alone would need guessing
whether that pid still lives, and pids are reused). A second process is refused with the first
one's pid. Locks are counted per process, so the CLI and the job inside it may both hold one.

>>> import tempfile
>>> run_dir = tempfile.mkdtemp()
>>> with hold_run_dir(run_dir), hold_run_dir(run_dir):  # the same process may take it again
...     pass
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections.abc import Iterator
from pathlib import Path

from l1flow_rl.errors import RunDirectoryError

__all__ = ["LOCK_NAME", "hold_run_dir"]

LOCK_NAME = ".lock"

#: lock files this process holds: path -> [file descriptor, how many holders]
_held: dict[Path, list[int]] = {}


def _acquire(lock: Path) -> None:
    if lock in _held:
        _held[lock][1] += 1
        return
    lock.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise RunDirectoryError(
            f"run_dir {str(lock.parent)!r} is in use by process {holder} (it holds {lock}); wait for "
            "that run to end, or choose another run_dir"
        ) from None
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    _held[lock] = [fd, 1]


def _release(lock: Path) -> None:
    entry = _held[lock]
    entry[1] -= 1
    if entry[1] == 0:
        del _held[lock]
        os.close(entry[0])  # closing the descriptor releases the flock


@contextlib.contextmanager
def hold_run_dir(run_dir: str | os.PathLike) -> Iterator[Path]:
    """Hold ``run_dir``'s lock for the ``with`` block (creating the directory); raises
    :class:`~l1flow_rl.errors.RunDirectoryError` naming the pid of the process that holds it."""
    lock = (Path(run_dir) / LOCK_NAME).resolve()
    _acquire(lock)
    try:
        yield lock
    finally:
        _release(lock)
