"""What every benchmark script shares: parsing its arguments, interleaved timing, and saving results
with what reruns them.

Each script prints a table and saves JSON under ``benchmarks/results/`` (read by ``benchmarks.report``
to build RESULTS.md and the README's tables). :func:`save_results` adds a ``provenance`` block: the
exact command, the resolved arguments, the commit and when it was measured; the scripts record the
machine themselves (``machine_info``), so figures from different machines are never mixed up.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch

from l1flow_rl.workspace.machine import machine_info

__all__ = [
    "RESULTS_DIR",
    "ROOT",
    "format_table",
    "git_commit",
    "interleaved",
    "machine_info",
    "parse_args",
    "provenance",
    "save_results",
    "timed",
]

#: the repository root: commands are recorded as run from it
ROOT = Path(__file__).resolve().parents[2]
#: where the scripts save their figures by default, and where the report reads them
RESULTS_DIR = ROOT / "benchmarks" / "results"
#: (module, argv, parsed arguments) of the script whose :func:`parse_args` ran last in this process
_current: tuple[str, list[str], argparse.Namespace] | None = None


def timed(fn: Callable[[], object], device: torch.device) -> tuple[float, float]:
    """(wall seconds, process CPU seconds) of one call; CUDA work is waited for."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    wall, cpu = time.perf_counter(), time.process_time()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - wall, time.process_time() - cpu


def interleaved(
    fns: Mapping[str, Callable[[], object]], rounds: int, device: torch.device, warmup: int = 1
) -> dict[str, dict[str, float]]:
    """Median wall and CPU milliseconds per call. The functions take turns each round, so that load
    drifting on a shared machine hits them alike."""
    for _ in range(warmup):
        for fn in fns.values():
            timed(fn, device)
    walls: dict[str, list[float]] = {k: [] for k in fns}
    cpus: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            w, c = timed(fn, device)
            walls[name].append(w)
            cpus[name].append(c)
    return {
        k: {"wall_ms": 1e3 * statistics.median(walls[k]), "cpu_ms": 1e3 * statistics.median(cpus[k])}
        for k in fns
    }


def parse_args(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> argparse.Namespace:
    """``parser.parse_args(argv)``, remembering the calling script's module, its command line and the
    parsed arguments, which :func:`save_results` records with the figures (as they are when saved:
    defaults included, and whatever ``--quick`` changed)."""
    global _current
    args = parser.parse_args(argv)
    spec = sys._getframe(1).f_globals.get("__spec__")
    module = spec.name if spec is not None else Path(sys.argv[0]).stem
    _current = (module, list(sys.argv[1:] if argv is None else argv), args)
    return args


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)  # paths, devices, enums: as the command line spells them


def git_commit(root: Path = ROOT) -> str | None:
    """The checked-out commit, with ``-dirty`` when tracked files differ from it; None outside git."""

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=True).stdout

    try:
        commit = git("rev-parse", "HEAD").strip()
        dirty = git("status", "--porcelain", "--untracked-files=no").strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return commit + ("-dirty" if dirty else "")


def provenance() -> dict[str, Any] | None:
    """What reruns the figures of the script whose :func:`parse_args` ran last: its exact command
    (from the repository root), its resolved arguments, the commit and the UTC time; None when no
    script parsed its arguments through :func:`parse_args`."""
    if _current is None:
        return None
    module, argv, args = _current
    return {
        "command": shlex.join(["python", "-m", module, *argv]),
        "config": _jsonable(vars(args)),
        "commit": git_commit(),
        "measured_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


def save_results(path: str | os.PathLike, figures: Mapping[str, Any]) -> Path:
    """Write ``figures`` as indented JSON (atomically: a crash leaves the old file), with the running
    script's :func:`provenance` under ``provenance`` unless ``figures`` carries its own."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    record = provenance()
    if record is not None and "provenance" not in figures:
        figures = {**figures, "provenance": record}
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(figures, indent=2) + "\n")
    os.replace(tmp, path)
    return path


def format_table(rows: list[Mapping[str, Any]], columns: list[str]) -> str:
    """A plain-text table of ``rows`` (dicts) over ``columns``."""
    cells = [[str(c) for c in columns]] + [[_fmt(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    lines = ["  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 100 else f"{value:.0f}"
    return str(value)
