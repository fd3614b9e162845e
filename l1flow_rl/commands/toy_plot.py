"""Figure for the toy: one heatmap of sampled trajectories per method, next to the demonstrations."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor

__all__ = ["plot_toy"]

_VALUE_BINS = 80
_UPSAMPLE = 8  # sub-steps per chunk step, so the heatmap shows curves rather than columns of dots


def _density(trajectories: Tensor, lim: float) -> Tensor:
    """Histogram [value bins, time] of trajectories [N, H], linearly interpolated between steps."""
    n, h = trajectories.shape
    fine = torch.nn.functional.interpolate(
        trajectories[:, None], size=(h - 1) * _UPSAMPLE + 1, mode="linear", align_corners=True
    )[:, 0]
    bins = ((fine + lim) / (2 * lim) * _VALUE_BINS).long().clamp(0, _VALUE_BINS - 1)  # [N, T]
    hist = torch.zeros(_VALUE_BINS, fine.shape[1])
    hist.scatter_add_(0, bins, torch.ones_like(fine))
    return hist / n


def plot_toy(
    modes: Tensor, samples: dict[str, tuple[str, Tensor]], results: dict[str, dict[str, Any]], path: Path
) -> None:
    """Write the figure: demonstrations, then each evaluation's samples with its mode shares."""
    # optional dependency (app extra): plots
    import matplotlib

    matplotlib.use("Agg")
    # optional dependency (app extra): pyplot, after the headless backend is chosen
    import matplotlib.pyplot as plt

    lim = 1.25 * float(modes.abs().max())
    h = modes.shape[-1]
    panels = [(f"Demonstrations ({modes.shape[0]} modes)", modes.repeat_interleave(256, dim=0), None)]
    panels += [(title, x, results[name]) for name, (title, x) in samples.items()]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.4), sharey=True, squeeze=False)
    extent = (0, h - 1, -lim, lim)
    for ax, (title, x, r) in zip(axes[0], panels):
        density = _density(x, lim)
        ax.imshow(density.sqrt().numpy(), origin="lower", aspect="auto", extent=extent, cmap="magma")
        for mode in modes:
            ax.plot(range(h), mode.numpy(), color="white", lw=0.8, ls="--", alpha=0.6)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("chunk step")
        ax.set_xticks(range(0, h, 5))
        if r is not None:
            ax.text(
                0.5,
                0.02,
                f"modes hit {r['modes_hit']}/{r['num_modes']} | off-mode {r['share_neither']:.0%}",
                transform=ax.transAxes,
                ha="center",
                va="bottom",
                color="white",
                fontsize=8,
            )
    axes[0][0].set_ylabel("action")
    fig.suptitle(
        f"One observation, {modes.shape[0]} demonstrated modes: where do the sampled chunks land?",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
