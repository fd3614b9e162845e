"""What a run leaves for a person to read: PNG plots of loss and success, and a summary table."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["format_summary", "save_history", "save_plots"]


def save_plots(
    history: Mapping[str, Sequence[float]], evals: Sequence[Mapping[str, Any]], run_dir: Path
) -> list[Path]:
    """``loss.png`` (training loss and LR against step) and ``success.png`` (eval success against step)."""
    # optional dependency (app extra): plots
    import matplotlib

    matplotlib.use("Agg")
    # optional dependency (app extra): plots
    import matplotlib.pyplot as plt

    written = []
    if history.get("step"):
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.plot(history["step"], history["loss"], lw=1, label="loss")
        ax.set_xlabel("step")
        ax.set_ylabel("training loss")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax2 = ax.twinx()
        ax2.plot(history["step"], history["lr"], color="tab:orange", lw=1, alpha=0.6, label="lr")
        ax2.set_ylabel("learning rate", color="tab:orange")
        ax.set_title("training loss")
        fig.tight_layout()
        fig.savefig(run_dir / "loss.png", dpi=120)
        plt.close(fig)
        written.append(run_dir / "loss.png")
    if evals:
        fig, ax = plt.subplots(figsize=(6, 3.5))
        _plot_success(ax, evals)
        fig.tight_layout()
        fig.savefig(run_dir / "success.png", dpi=120)
        plt.close(fig)
        written.append(run_dir / "success.png")
    return written


def _plot_success(ax: Any, evals: Sequence[Mapping[str, Any]]) -> None:
    """Validation as curves (labelled with its episode count), the test as one point per metric at
    the step of the weights it scored, with its 95 % interval: the two splits answer different
    questions (which checkpoint to ship; how good the shipped one is) and use different seeds."""
    val = [e for e in evals if e.get("split", "val") == "val"]
    test = [e for e in evals if e.get("split") == "test"]
    for key, style in (("success_once", "o-"), ("success_at_end", "s--")):
        if val:
            label = f"validation {key} ({val[-1].get('episodes', '?')} episodes)"
            ax.plot([e["step"] for e in val], [e[key] for e in val], style, lw=1, label=label)
    for row in test:
        step = row.get("weights_step", row["step"])
        for key, marker, color in (("success_once", "*", "tab:red"), ("success_at_end", "P", "tab:purple")):
            low, high = row.get("ci95", {}).get(key, (row[key], row[key]))
            err = [[row[key] - low], [high - row[key]]]
            label = f"test {key} ({row.get('episodes', '?')} episodes, weights of step {step})"
            ax.errorbar([step], [row[key]], yerr=err, fmt=marker, color=color, ms=9, capsize=4, label=label)
    ax.set_ylim(-0.05, 1.05)
    ax.set_xlabel("step")
    ax.set_ylabel("success rate")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    ax.set_title("success: validation, and the test of the chosen weights", fontsize=10)


def save_history(
    history: Mapping[str, Sequence[float]],
    evals: Sequence[Mapping[str, Any]],
    run_dir: Path,
    **records: Sequence[Any],
) -> Path:
    """``history.json``: the logged training curve, every evaluation during training (what
    ``benchmarks/`` reads for convergence curves) and the job's other ``records`` (e.g. rounds)."""
    path = run_dir / "history.json"
    body = {"train": dict(history), "evals": list(evals), **{k: list(v) for k, v in records.items()}}
    path.write_text(json.dumps(body, indent=1) + "\n")
    return path


def format_summary(rows: Mapping[str, Any]) -> str:
    """A two-column table of the run's headline figures."""
    width = max(len(k) for k in rows)
    lines = ["-" * (width + 24)]
    for key, value in rows.items():
        if isinstance(value, float):
            shown = f"{value:.3f}"
        elif isinstance(value, Mapping):  # e.g. the machine: its values on one line, keys implied
            shown = ", ".join(f"{k} {v}" for k, v in value.items())
        else:
            shown = str(value)
        lines.append(f"{key:<{width}}  {shown}")
    lines.append(lines[0])
    return "\n".join(lines)
