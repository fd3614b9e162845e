"""What a core install (``pip install l1flow-rl``, no extras) holds, read from the installed metadata:
the distributions it brings and the top-level modules that only the extras bring. Used in this
process (tests/unit/project/test_import_graph.py) and inside the interpreter that hides the extras
(tests/unit/project/test_core_install.py), so it imports nothing outside the standard library and
packaging."""

from __future__ import annotations

import importlib.metadata as md
import re
import sys

from packaging.requirements import Requirement

__all__ = ["core_distributions", "extra_top_levels", "norm"]


def norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def core_distributions(root: str = "l1flow-rl") -> set[str]:
    """``root`` and its requirements without extras, transitively (normalised names)."""
    seen, todo = set(), [norm(root)]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        try:
            requires = md.distribution(name).requires or []
        except md.PackageNotFoundError:
            continue
        for line in requires:
            req = Requirement(line)
            if req.marker is None or req.marker.evaluate({"extra": ""}):
                todo.append(norm(req.name))
    return seen


def extra_top_levels(core: set[str] | None = None) -> set[str]:
    """The installed top-level modules that no core distribution provides (the standard library is
    not among them)."""
    core = core_distributions() if core is None else core
    return {
        top
        for top, dists in md.packages_distributions().items()
        if top not in sys.stdlib_module_names and not any(norm(d) in core for d in dists)
    }
