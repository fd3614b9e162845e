"""What a run leaves for a person to read: PNG plots of loss and success, and a summary table."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["format_summary", "save_history", "save_plots"]


def save_plots(
    history: Mapping[str, Sequence[float]], evals: Sequence[Mapping[str, Any]], run_dir: Path
) -> list[Path]:
    """``loss.png`` (training loss and LR against step) and ``success.png`` (eval success against step)."""
    import matplotlib

    matplotlib.use("Agg")
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
        steps = [e["step"] for e in evals]
        ax.plot(steps, [e["success_once"] for e in evals], "o-", label="success_once")
        ax.plot(steps, [e["success_at_end"] for e in evals], "s--", label="success_at_end")
        ax.set_ylim(-0.05, 1.05)
        ax.set_xlabel("step")
        ax.set_ylabel("success rate")
        ax.legend()
        ax.grid(alpha=0.3)
        ax.set_title(f"evaluation ({evals[-1].get('episodes', '?')} episodes)")
        fig.tight_layout()
        fig.savefig(run_dir / "success.png", dpi=120)
        plt.close(fig)
        written.append(run_dir / "success.png")
    return written


def save_history(
    history: Mapping[str, Sequence[float]],
    evals: Sequence[Mapping[str, Any]],
    run_dir: Path,
    **records: Sequence[Any],
) -> Path:
    """``history.json``: the logged training curve, every evaluation during training (what
    ``benchmarks/`` reads for convergence curves) and the job's other ``records`` (e.g. rounds)."""
    import json

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
