"""The measurements behind the defaults that a measurement chose, read from the saved JSON.

A config file states its default and points to ``benchmarks/RESULTS.md`` ("Defaults and the
measurements behind them"); the figures are rendered here from the results files, so a re-run
updates them and no comment carries a number that can go stale. To add a default: a function that
reads the results folder and returns its text and source files (None when a file is absent), and a
row in ``EVIDENCE``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["EVIDENCE", "Evidence", "evidence_table"]

Measured = tuple[str, list[str]] | None


@dataclass(frozen=True)
class Evidence:
    default: str  # the setting as a user would write it
    where: str  # the config file that sets it
    measure: Callable[[Path], Measured]  # (what was measured, its source files)


def _load(path: Path) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    data = json.loads(path.read_text())
    return None if not isinstance(data, dict) or data.get("quick") else data


def _ci(ci: list[float] | None) -> str:
    return f" [{ci[0]:.2f}, {ci[1]:.2f}]" if ci else ""


def _mean_curve(curves: list[list[list[float]]]) -> str:
    """The validation curve averaged over seeds at the steps every seed reached."""
    steps = sorted(set.intersection(*({s for s, _ in c} for c in curves)))
    means = [sum(dict(c)[s] for c in curves) / len(curves) for s in steps]
    return ", ".join(f"{v:.2f} at {s:,}" for s, v in zip(steps, means))


def _seeds(n: int) -> str:
    return f"{n} seed{'s' * (n != 1)}"


def main_job_budget(results: Path) -> Measured:
    d = _load(results / "main_job.json")
    if d is None or d.get("quick"):
        return None
    first = d["runs"][0]
    text = (
        f"demonstrations, {first['steps']:,} training steps and a {first['eval_episodes']}-episode test "
        f"evaluation in at most {d['wall_seconds_max']:,.0f} s ({d['wall_over_budget_max']:.2f} of the "
        f"{d['budget_seconds'] / 60:.0f}-minute budget) over {_seeds(len(d['runs']))}; success_once "
        + ", ".join(f"{r['success_once']:.2f}{_ci(r.get('success_once_ci95'))}" for r in d["runs"])
    )
    return text, ["main_job.json"]


def stackcube_demos(results: Path) -> Measured:
    parts, sources = [], []
    for name in ("success_stackcube_budget.json", "success_stackcube.json"):
        d = _load(results / name)
        block = ((d or {}).get("tasks") or {}).get("maniskill_stackcube", {}).get("l1flow")
        if block is None:
            continue
        a, n = d["args"], block["success_once"]["n"]
        curve = _mean_curve(block["curves"])
        parts.append(
            f"{a['demos']} demonstrations, {_seeds(n)}: validation success_once {curve} steps; "
            f"test {block['success_once']['mean']:.2f} after {a['steps']:,} steps"
        )
        sources.append(name)
    return ("; ".join(parts), sources) if parts else None


def pusht_budget(results: Path) -> Measured:
    d = _load(results / "success_pusht.json")
    block = ((d or {}).get("tasks") or {}).get("pusht", {}).get("l1flow")
    if block is None:
        return None
    metric, n = block.get("metric", "success_once"), block["success_once"]["n"]
    cpu = [r["cpu_seconds"] for r in block["per_seed"] if r.get("cpu_seconds")]
    text = (
        f"{d['args']['demos']} demonstrations, {_seeds(n)}: validation {metric} "
        f"{_mean_curve(block['curves'])} steps; test {metric} {block[metric]['mean']:.3f}"
    )
    if cpu:
        text += f"; {sum(cpu) / len(cpu) / 60:.0f} CPU-minutes per run"
    return text, ["success_pusht.json"]


def rgb_budget(results: Path) -> Measured:
    d = _load(results / "training_images.json")
    runs = [r for r in (d or {}).get("runs", []) if r.get("train_seconds") and r.get("steps")]
    if not runs:
        return None
    texts = [
        f"{r['task']}, {r['demos']} demonstrations: {r['steps']:,} steps in {r['train_seconds']:,.0f} s of "
        f"training ({r['train_seconds'] / r['steps']:.2f} s per step), {r['wall_seconds']:,.0f} s in all; "
        f"success_once {r['success_once']:.2f}{_ci(r.get('success_once_ci95'))} "
        f"on {r['episodes']} test episodes"
        for r in runs
    ]
    return "; ".join(texts), ["training_images.json"]


#: the defaults a measurement chose, and where each is set
EVIDENCE = [
    Evidence("`train=cpu` (the main job's budget)", "configs/train/cpu.yaml", main_job_budget),
    Evidence(
        "300 demonstrations for StackCube (`demos=n300`)",
        "configs/task/maniskill_stackcube.yaml",
        stackcube_demos,
    ),
    Evidence("8,000 steps for PushT (`train=cpu_long`)", "configs/train/cpu_long.yaml", pusht_budget),
    Evidence(
        "image tasks: batch 32, 2,000 steps (`train=cpu_rgb`)", "configs/train/cpu_rgb.yaml", rgb_budget
    ),
]


def evidence_table(results: Path) -> str | None:
    """One row per default whose measurement is saved, or None when none is."""
    rows = []
    for e in EVIDENCE:
        measured = e.measure(results)
        if measured is not None:
            text, sources = measured
            rows.append(
                f"| {e.default} | `{e.where}` | {text} | " + ", ".join(f"`{s}`" for s in sources) + " |"
            )
    if not rows:
        return None
    return "\n".join(["| default | set in | measured | source |", "|---|---|---|---|", *rows])
