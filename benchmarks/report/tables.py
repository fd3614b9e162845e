"""What every section of the report shares: number formatting, Markdown tables, and the line that
names a results file, when it was measured, on what machine and with what command."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

__all__ = ["interval", "link", "machine_text", "num", "source_line", "table"]


def num(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, float):
        return f"{value:,.0f}" if abs(value) >= 1000 else f"{value:.{digits}g}"
    return str(value)


def table(header: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(num(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def interval(ci: list | None) -> str:
    return f"[{ci[0]:.2f}, {ci[1]:.2f}]" if ci else "–"


def link(target: Path, doc: Path) -> str:
    """``target`` as a link from the document ``doc`` (Markdown resolves links from its folder)."""
    return Path(os.path.relpath(target, doc.parent)).as_posix()


def _runs_machines(d: dict) -> str | None:
    """The machines a collected success file's runs recorded as they ended (None: none recorded)."""
    seeds = [
        r
        for by_policy in (d.get("tasks") or {}).values()
        for entry in by_policy.values()
        for r in entry.get("per_seed", [])
    ]
    machines = [r["machine"] for r in seeds if isinstance(r.get("machine"), dict)]
    if not machines:
        return None
    kinds = sorted({f"{m.get('cpu', '?')}, torch threads {m.get('torch_threads')}" for m in machines})
    loads = [m["load_average_1min"] for m in machines if "load_average_1min" in m]
    text = "; ".join(kinds)
    if loads:
        text += f", load {min(loads)}-{max(loads)} as they ended"
    if len(machines) < len(seeds):
        text += f" ({len(machines)} of {len(seeds)} seed records carry it)"
    return text


def machine_text(d: dict) -> str:
    m = d.get("machine") or d.get("machine_at_start")
    if m is None and "cpu_count" in d:
        load = d.get("loadavg_before") or d.get("loadavg_after")
        return f"{d['cpu_count']} cores" + (f", load {load[0]:.2f}" if load else "")
    if isinstance(m, dict) and (d.get("args") or {}).get("collect_only"):
        # the collecting process's threads and load say nothing of the runs, which trained earlier
        where = f"{m.get('cpu', '?')}, {m.get('cores')} cores (where the runs were collected"
        runs = _runs_machines(d)
        if runs is None:
            return f"{where}; they trained earlier, and this file holds none of their thread counts or load)"
        return f"{where}); the runs: {runs}"
    if isinstance(m, dict):
        parts = [m.get("cpu", "?"), f"{m.get('cores')} cores", f"torch threads {m.get('torch_threads')}"]
        if "load_average_1min" in m:
            parts.append(f"load {m['load_average_1min']}")
        if m.get("gpu"):
            parts += [m["gpu"], f"torch {m.get('torch')}"]
        return ", ".join(str(p) for p in parts)
    return "not recorded" if m is None else str(m)


def source_line(path: Path, data: dict, doc: Path) -> str:
    """The file (linked), when it was measured, its machine, and the command and commit that rerun it
    where the file records them (files saved before the scripts recorded them say so). A file
    collected from a grid's runs names the grid's command, the runs' commits and launchers, then the
    command that collected it."""
    from benchmarks.report.staleness import measured_range

    record = data.get("provenance") or {}
    runs = record.get("runs") if isinstance(record.get("runs"), dict) else None
    when = measured_range(data) or "not recorded"
    text = f"[`{path.name}`]({link(path, doc)}): measured: {when}; machine: {machine_text(data)}"
    if runs is not None:
        commits = ", ".join(f"`{c[:12]}`" for c in runs.get("commits") or []) or "not recorded"
        text += f"; runs: `{runs['command']}`" if runs.get("command") else "; runs"
        text += f" at commit {commits}"
        if runs.get("launchers"):
            text += f" (launcher {', '.join(runs['launchers'])})"
        if record.get("command"):
            text += f"; collected by `{record['command']}`"
        return text + "."
    command = record.get("command") or data.get("command")
    if command:
        text += f"; command: `{command}`"
    if record.get("commit"):
        text += f"; commit `{record['commit'][:12]}`"
    return text + "."
