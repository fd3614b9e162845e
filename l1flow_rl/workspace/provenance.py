"""What a run records of the code and the launcher behind its figures (``provenance`` in its
``eval.json`` and ``summary.json``), so that a figure read later can be dated against the code.

- ``commits``: the commit of the library's source tree at each invocation of the run (one, unless a
  resume came at another commit), with ``-dirty`` where tracked files differed from it; empty when
  the library is not a git checkout (an installed wheel).
- ``launcher``: the hydra launcher that ran the job (``basic``, ``joblib``, ``submitit_slurm``, ...;
  None outside a hydra job).
- ``resumed_at``: the steps the run was resumed from (a stopped run continued; empty: one go).
- ``measured_at``: when the figures were written (UTC).

``benchmarks/report`` marks a published table stale when the code that produced it changed after
its commits.
"""

from __future__ import annotations

import subprocess
from datetime import datetime, timezone
from functools import cache
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig

__all__ = ["launcher_name", "run_provenance", "source_commit"]

#: the folder holding the l1flow_rl package (the repository root in a checkout)
_SOURCE_ROOT = Path(__file__).resolve().parents[2]


@cache
def source_commit(root: Path = _SOURCE_ROOT) -> str | None:
    """The commit checked out at ``root``, with ``-dirty`` when tracked files differ from it; None
    when ``root`` is not in a git work tree or git is missing (read once per process)."""

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", *args], cwd=root, capture_output=True, text=True, check=True, timeout=30
        ).stdout

    try:
        commit = git("rev-parse", "HEAD").strip()
        dirty = git("status", "--porcelain", "--untracked-files=no").strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return commit + ("-dirty" if dirty else "") if commit else None


def launcher_name() -> str | None:
    """The running hydra job's launcher, by its config name where hydra records one (``joblib``,
    ``submitit_slurm``), else its class; None outside a hydra job."""
    if not HydraConfig.initialized():
        return None
    hydra = HydraConfig.get()
    choice = hydra.runtime.choices.get("hydra/launcher")
    if choice:
        return str(choice)
    target = hydra.launcher.get("_target_")
    return str(target).rsplit(".", 1)[-1] if target else None


def run_provenance(commits: list[str] | None = None, resumed_at: list[int] | None = None) -> dict[str, Any]:
    """The ``provenance`` block of a run's records: ``commits`` (default: this process's), the
    launcher, the steps it was resumed from and the time."""
    if commits is None:
        commits = [c] if (c := source_commit()) else []
    return {
        "commits": list(commits),
        "launcher": launcher_name(),
        "resumed_at": list(resumed_at or []),
        "measured_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
