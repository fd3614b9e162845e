"""A switch for the input checks that read tensor values (NaN/Inf, ranges) on the host.

Reading a value of a GPU tensor waits for the device: one host synchronisation per check, every
training step. The training loop turns these checks off for batches whose values were already
checked where they entered the library (``l1flow_rl.data.episodes.check_finite`` when episodes are
loaded) and for flow times its loss draws itself. Checks of keys, shapes and dtypes read no values
and always run. By default every check runs, so data a user passes directly is still checked (the
same idea as ``torch.distributions.Distribution.set_default_validate_args``).

Examples:
    >>> value_checks_enabled()
    True
    >>> with skip_value_checks():
    ...     value_checks_enabled()
    False
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from contextvars import ContextVar

__all__ = ["skip_value_checks", "value_checks_enabled"]

_ENABLED: ContextVar[bool] = ContextVar("l1flow_rl_value_checks", default=True)


def value_checks_enabled() -> bool:
    """Whether the input checks that read tensor values run (True outside :func:`skip_value_checks`)."""
    return _ENABLED.get()


@contextlib.contextmanager
def skip_value_checks() -> Iterator[None]:
    """Skip the value-reading input checks inside this block (for data checked on the way in)."""
    token = _ENABLED.set(False)
    try:
        yield
    finally:
        _ENABLED.reset(token)
