"""Errors a user can fix: a file, a config value, a checkpoint, a run directory.

The ``l1flow-rl`` command prints an error of this family as one line,
``l1flow-rl <command>: <message>``, and exits with code 2; any other exception is a bug and keeps
its traceback. So the message must say what is wrong, naming the file, key or field, and what to
do. The family is decided by type, never by message text. :class:`RunPreempted` is no error but
is reported the same way: a run stopped by a signal, with a checkpoint to resume from. This module
imports nothing of the package, so that every layer (data, config, workspace) can raise these.

>>> try:
...     raise RunDirectoryError("runs/x is in use by process 12; wait for it or choose another run_dir")
... except UserInputError as err:
...     print(f"l1flow-rl train: {err}")
l1flow-rl train: runs/x is in use by process 12; wait for it or choose another run_dir
"""

from __future__ import annotations

import signal
from pathlib import Path

__all__ = ["CheckpointReadError", "RunDirectoryError", "RunDivergedError", "RunPreempted", "UserInputError"]


class UserInputError(Exception):
    """Bad input the user can correct; its message is the whole story (no traceback needed)."""


class CheckpointReadError(UserInputError, ValueError):
    """A checkpoint file that is missing, truncated, or not one that l1flow-rl wrote."""


class RunDirectoryError(UserInputError):
    """The run directory cannot take this run: in use by another process, already holding a run
    (without ``resume=true``), or holding nothing to resume."""


class RunDivergedError(UserInputError, FloatingPointError):
    """Training produced a non-finite loss or gradient norm; the message names the step, the
    terms, and the last (finite) checkpoint."""


class RunPreempted(BaseException):
    """A stop signal arrived; the run wrote a checkpoint at ``step`` and can be resumed.

    A ``BaseException``, like ``KeyboardInterrupt``: a sweep stops with it instead of starting its
    next job in a process that is about to be killed. ``exit_code`` is the shell's for the signal.
    """

    def __init__(self, signum: int, step: int, run_dir: Path, checkpoint: Path | None) -> None:
        self.signum, self.step, self.run_dir, self.checkpoint = signum, step, Path(run_dir), checkpoint
        self.exit_code = 128 + signum
        saved = f"checkpoint {checkpoint} holds it" if checkpoint else "nothing to save before step 1"
        super().__init__(
            f"stopped by {signal.Signals(signum).name} at step {step}; {saved}. Resume with the same "
            f"command plus resume=true run_dir={self.run_dir}"
        )
