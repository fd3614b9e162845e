"""What every benchmark script shares: the machine it ran on, interleaved timing, and saving results.

Each script prints a table, saves JSON under ``benchmarks/results/`` (read by ``benchmarks.report``
to build the README's tables) and records the machine, so figures from different machines are
never mixed up.
"""

from __future__ import annotations

import json
import os
import statistics
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch

from l1flow_rl.workspace.machine import machine_info

__all__ = ["format_table", "interleaved", "machine_info", "save_results", "timed"]


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


def save_results(path: str | os.PathLike, figures: Mapping[str, Any]) -> Path:
    """Write ``figures`` as indented JSON (atomically: a crash leaves the old file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
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
