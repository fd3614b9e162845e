"""The success curves' figure (the paper's Figure 4 style), drawn by ``bench_success`` and the report."""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = ["METHOD_COLORS", "plot_success_curves"]

#: the success curves' colour of each method (matplotlib's default cycle)
METHOD_COLORS = {"l1flow": "C0", "flow": "C1", "ddpm": "C2", "regression": "C3"}


def plot_success_curves(results: dict[str, dict[str, Any]], path: Path, columns: int = 3) -> None:
    """Success against training step, one panel per task: each method's mean over seeds with its
    min-max band, from a success file's ``tasks`` blocks; ``columns`` panels a row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(results)
    ncols = min(columns, len(tasks))
    nrows = -(-len(tasks) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.5 * ncols, 3.6 * nrows), squeeze=False)
    for ax, task in zip(axes.flat, tasks):
        for method, block in results[task].items():
            curves = [c for c in block["curves"] if c]
            if not curves:
                continue
            steps = sorted({s for c in curves for s, _ in c})
            values = [[v for c in curves if (v := dict(c).get(s)) is not None] for s in steps]
            mean = [sum(vs) / len(vs) for vs in values]
            lo, hi = [min(vs) for vs in values], [max(vs) for vs in values]
            # one colour per method in every panel and figure
            color = METHOD_COLORS.get(method, f"C{len(METHOD_COLORS) + sum(map(ord, method)) % 6}")
            label = method + (f" (validation: {v})" if (v := block.get("validation_sampler")) else "")
            ax.plot(steps, mean, "o-", ms=3, label=label, color=color)
            ax.fill_between(steps, lo, hi, color=color, alpha=0.15)
        ax.set_title(task, fontsize=9)
        ax.set_xlabel("training step")
        metric = next((b["metric"] for b in results[task].values()), "success_once")
        ax.set_ylabel(f"{metric} (validation seeds)")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(tasks) :]:
        ax.set_visible(False)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
