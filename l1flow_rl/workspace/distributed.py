"""torchrun support: the process group, ranks and devices, and rank-0-only work that cannot strand
the other ranks.

Rank 0 owns demonstrations, evaluation, checkpoints and logs; every rank trains on its own sample
stream. Two rules keep a multi-process run from hanging:

- Rank-0-only work runs through :func:`run_on_rank0`. The others wait for its outcome on a
  separate gloo group whose timeout (:data:`STATUS_TIMEOUT`) outlasts any demonstration generation
  or evaluation, instead of waiting in a training collective that the default process-group timeout
  would cut. Rank 0 then broadcasts either the result or its error, and every rank ends with that
  error rather than a "connection closed" from a collective.
- Work every rank does on its own (loading data, building the model) ends with
  :func:`raise_if_any_failed`, so a failure on one rank is raised on all of them before the first
  training collective.

Under a single process both helpers run the work directly.
"""

from __future__ import annotations

import os
import traceback
from collections.abc import Callable
from datetime import timedelta
from typing import Any, TypeVar

import torch
import torch.distributed as dist

from l1flow_rl.utils.device import resolve_device  # re-exported: the jobs read device= through it

__all__ = [
    "STATUS_TIMEOUT",
    "RankFailedError",
    "init_distributed",
    "raise_if_any_failed",
    "resolve_device",
    "run_on_every_rank",
    "run_on_rank0",
]

T = TypeVar("T")

#: How long the other ranks wait for rank 0's status: longer than any demonstration generation or
#: evaluation; a rank that dies is noticed sooner, by torchrun, which then stops the others.
STATUS_TIMEOUT = timedelta(hours=24)

_status_group: Any = None


class RankFailedError(RuntimeError):
    """Another rank failed; the message carries its error, and the traceback its traceback."""


def init_distributed(status_timeout: timedelta = STATUS_TIMEOUT) -> tuple[int, int]:
    """(rank, world_size); under torchrun, initialises the process group (NCCL on CUDA, else gloo)
    and the gloo group rank 0 reports its status on."""
    global _status_group
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    if not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    if _status_group is None:
        _status_group = dist.new_group(backend="gloo", timeout=status_timeout)
    return dist.get_rank(), world


def _distributed() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def _describe(err: BaseException) -> tuple[str, str]:
    return f"{type(err).__name__}: {err}", "".join(traceback.format_exception(err))


def run_on_rank0(work: Callable[[], T], what: str) -> T:
    """Run ``work`` on rank 0 only and return its result on every rank.

    If ``work`` raises, rank 0 re-raises its exception and every other rank raises
    :class:`RankFailedError` naming ``what`` and rank 0's error. The result must be picklable.

    Example:
        >>> run_on_rank0(lambda: 41 + 1, "adding")  # one process: runs in place
        42
    """
    if not _distributed():
        return work()
    rank = dist.get_rank()
    status: list[Any] = [None]
    error: BaseException | None = None
    if rank == 0:
        try:
            status = [("ok", work())]
        except BaseException as err:  # KeyboardInterrupt too: the others must not wait for ever
            error = err
            status = [("error", *_describe(err))]
    dist.broadcast_object_list(status, src=0, group=_status_group)
    if error is not None:
        raise error
    kind, *payload = status[0]
    if kind == "error":
        message, remote_traceback = payload
        raise RankFailedError(
            f"rank 0 failed while {what}: {message}\n\nrank 0's traceback:\n{remote_traceback}"
        )
    return payload[0]


def raise_if_any_failed(error: BaseException | None, what: str) -> None:
    """Every rank calls this after work it did on its own, passing the exception it caught (or
    None). A rank that failed re-raises its own error; the others raise :class:`RankFailedError`
    naming the first rank that failed and its error."""
    if not _distributed():
        if error is not None:
            raise error
        return
    mine = None if error is None else _describe(error)
    statuses: list[Any] = [None] * dist.get_world_size()
    dist.all_gather_object(statuses, mine, group=_status_group)
    if error is not None:
        raise error
    for rank, status in enumerate(statuses):
        if status is not None:
            message, remote_traceback = status
            raise RankFailedError(
                f"rank {rank} failed while {what}: {message}\n\nrank {rank}'s traceback:\n{remote_traceback}"
            )


def run_on_every_rank(work: Callable[[], T], what: str) -> T:
    """Run ``work`` on every rank; if it fails on any, every rank raises (see
    :func:`raise_if_any_failed`) before the next collective could strand the others.

    Example:
        >>> run_on_every_rank(lambda: "ready", "loading")
        'ready'
    """
    try:
        result = work()
    except Exception as err:
        raise_if_any_failed(err, what)
        raise  # unreachable: raise_if_any_failed re-raises err
    raise_if_any_failed(None, what)
    return result
