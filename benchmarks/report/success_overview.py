"""Every success file's methods in one table and one figure (the paper's Table 2 and Figure 4).

Each ``bench_success`` invocation saves one file per task group, with its own setting (demos,
steps, seeds); a reader comparing methods across tasks wants them side by side. ``benchmarks.report``
puts this table after the claims: one row per task and setting, one column per method, each cell
the mean over seeds with Wilson's 95 % interval over the seeds' test episodes pooled. The figure
(``success_overview.png``) gathers the validation curves of every file, one panel per row.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["COLUMNS", "overview_figure", "overview_table"]

#: the table's columns: a success file's method label -> its heading
COLUMNS = {
    "l1flow": "L1 Flow (2 NFE)",
    "flow": "flow (Euler 10)",
    "ddpm": "DDPM-100",
    "ddpm_ddim16": "DDIM-16",
    "regression": "regression",
}


def _settings(results: Path) -> list[tuple[str, str, dict[str, Any], dict[str, Any]]]:
    """(file name, task, the file's args, the task's method blocks) for every full-run success file
    whose task has two or more of the table's methods (a file of DDPM's seeds alone, with its DDIM-16
    re-scoring, counts: its row sits under the same task's other file)."""
    found = []
    for path in sorted(results.glob("success_*.json")):
        data = json.loads(path.read_text())
        if not isinstance(data, dict) or data.get("quick"):
            continue
        for task, block in data.get("tasks", {}).items():
            if len(set(block) & set(COLUMNS)) > 1:
                found.append((path.name, task, data.get("args") or {}, block))
    return found


def _cell(block: dict[str, Any] | None) -> str:
    from benchmarks.report.claims import pooled_interval

    if block is None:
        return "–"
    metric = block.get("metric", "success_once")
    mean = block[metric]["mean"]
    if metric != "success_once":  # PushT: Diffusion Policy's score has no pooled interval here
        return f"{mean:.3f} ({metric}; success {block['success_once']['mean']:.2f})"
    ci = pooled_interval(block["per_seed"])
    return f"{mean:.3f} [{ci[0]:.2f}, {ci[1]:.2f}]" if ci else f"{mean:.3f}"


def overview_table(results: Path) -> str | None:
    """The Table-2-style markdown table, or None when no success file compares methods."""
    settings = _settings(results)
    if not settings:
        return None
    lines = [
        "| task | setting | " + " | ".join(COLUMNS.values()) + " |",
        "|---|---|" + "---|" * len(COLUMNS),
    ]
    for name, task, args, block in settings:
        seeds = next(block[k]["success_once"]["n"] for k in COLUMNS if k in block)
        setting = f"{args.get('demos', '?')} demos, {args.get('steps', '?'):,} steps, {seeds} seed"
        setting += "s" * (seeds != 1) + "".join(f", `{o}`" for o in args.get("extra") or []) + f" (`{name}`)"
        means = {k: b[b.get("metric", "success_once")]["mean"] for k, b in block.items() if k in COLUMNS}
        best = max(means.values())
        bold = {k for k, m in means.items() if m == best and best > 0}  # nothing to single out at 0
        cells = [f"**{_cell(block[k])}**" if k in bold else _cell(block.get(k)) for k in COLUMNS]
        lines.append(f"| {task} | {setting} | " + " | ".join(cells) + " |")
    note = (
        "Mean over seeds of each seed's test figure (success_once, or Diffusion Policy's score where "
        "the protocol reports it), with Wilson's 95 % interval over the seeds' test episodes pooled; "
        "the highest non-zero mean in bold. DDIM-16 is the DDPM network re-scored under a 16-step DDIM "
        "sampler, not a separate training. Each file's section below gives its per-seed figures, "
        "budget and the ManiSkill-protocol re-scorings."
    )
    return "\n".join(lines) + "\n\n" + note


def overview_figure(results: Path, out: Path) -> bool:
    """Save every comparing file's validation curves in one figure; False when there are none."""
    from benchmarks.lib.figures import plot_success_curves

    settings = _settings(results)
    if not settings:
        return False
    # one panel per table row: two files of one task (a default sweep and an ablation) keep both
    panels = {
        f"{task} ({args.get('demos', '?')} demos, {Path(name).stem.removeprefix('success_')})": {
            k: b for k, b in block.items() if b.get("curves")
        }
        for name, task, args, block in settings
    }
    plot_success_curves(panels, out)
    return True
