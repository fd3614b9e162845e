"""The one rule every name -> plug-in registry of the package keeps (encoders, experts, protocols).

A name is registered once: registering a different object under a taken name is an error unless
``replace``, and registering the same object again is a no-op (a module imported twice is harmless).
This module imports nothing of the package, so that every registry can use it.
"""

from __future__ import annotations

from typing import TypeVar

__all__ = ["register_unique"]

T = TypeVar("T")


def register_unique(table: dict[str, T], key: str, item: T, *, replace: bool, what: str) -> T:
    """Put ``item`` under ``key`` in ``table`` and return it.

    Raises ``ValueError("<what> '<key>' is already registered")`` where another object holds
    ``key`` and ``replace`` is False.

    >>> table = {}
    >>> register_unique(table, "a", 1, replace=False, what="a number named")
    1
    >>> register_unique(table, "a", 2, replace=False, what="a number named")
    Traceback (most recent call last):
    ...
    ValueError: a number named 'a' is already registered
    """
    if key in table and not replace and table[key] is not item:
        raise ValueError(f"{what} {key!r} is already registered")
    table[key] = item
    return item
