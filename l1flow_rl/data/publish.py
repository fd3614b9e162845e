"""Publishing a finished directory under its final name, safely when several processes race to make
the same cache (runs trained side by side on one data_dir)."""

from __future__ import annotations

import errno
import os
from pathlib import Path

__all__ = ["publish_dir"]


def publish_dir(tmp: Path, target: Path) -> bool:
    """Rename the complete directory ``tmp`` to ``target``; True when ours is the published copy.

    An empty ``target`` is replaced. When another process published a non-empty ``target`` first,
    returns False and leaves both in place (the caller discards ``tmp`` and reads ``target``, after
    checking it holds what it expects)."""
    try:
        os.replace(tmp, target)  # atomic: a half-written copy never carries the final name
    except OSError as err:
        if err.errno not in (errno.ENOTEMPTY, errno.EEXIST) or not target.is_dir():
            raise
        if any(target.iterdir()):
            return False  # lost the race to an identical build
        target.rmdir()
        os.replace(tmp, target)
    return True
