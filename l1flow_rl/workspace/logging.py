"""The run's TorchRL logger (CSV, TensorBoard or W&B) under ``run_dir/logs``, and what evaluations
send to it: every scalar metric with its 95 % interval, and the videos."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from torchrl.record.loggers import get_logger

from l1flow_rl.config.train import LOGGERS
from l1flow_rl.evaluation.videos import log_videos

__all__ = ["EVAL_SCALARS", "log_evaluation", "logger_kwargs", "make_logger"]

#: scalars of an evaluation result that are logged besides its metrics (means and intervals)
EVAL_SCALARS = ("latency_ms_median", "latency_ms_p90", "nfe_per_chunk", "errors", "episodes", "wall_s")


def logger_kwargs(
    kind: str,
    run_dir: Path,
    *,
    project: str = "l1flow-rl",
    group: str | None = None,
    run_name: str | None = None,
    default_name: str = "train",
    config: dict | None = None,
) -> dict[str, Any]:
    """Keyword arguments of TorchRL's ``get_logger`` for ``train.logger=kind``: logs under
    ``run_dir/logs``, named ``run_name`` (default: ``default_name``, the job's; on W&B the run
    directory's name); W&B also gets its project, group and the run's config."""
    if kind not in LOGGERS:
        raise ValueError(f"train.logger={kind!r}; expected one of {list(LOGGERS)}")
    kwargs: dict[str, Any] = {
        "logger_type": kind,
        "logger_name": str(run_dir / "logs"),
        "experiment_name": run_name or (default_name if kind != "wandb" else run_dir.name),
    }
    if kind == "wandb":
        wandb = {"project": project, "config": config or {}}
        if group:
            wandb["group"] = group
        kwargs["wandb_kwargs"] = wandb
    return kwargs


def make_logger(kind: str, run_dir: Path, state: dict | None, **options: Any):
    """The run's logger; ``state`` (a saved ``logger.state_dict()``) resumes it. ``options`` are
    :func:`logger_kwargs`' (project, group, run_name, default_name, config)."""
    kwargs = logger_kwargs(kind, run_dir, **options)
    if state is not None:
        # TorchRL reopens the saved log_dir: a run copied, moved or resumed with another run_dir
        # went on logging into its old directory (seen: a copied fine-tune appended to the original's CSVs)
        state = {**state, "log_dir": kwargs["logger_name"]}
    return get_logger(kwargs.pop("logger_type"), state_dict=state, **kwargs)


def log_evaluation(logger: Any, result: dict[str, Any], step: int, prefix: str) -> list[str]:
    """Log every metric of an evaluation result as ``{prefix}/{name}`` with ``{prefix}/{name}_ci95_low``
    and ``_high``, the scalars in :data:`EVAL_SCALARS`, and its videos. Returns the names logged."""
    logged = []

    def scalar(name: str, value: Any) -> None:
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            logger.log_scalar(f"{prefix}/{name}", float(value), step=step)
            logged.append(f"{prefix}/{name}")

    for name, (low, high) in result.get("ci95", {}).items():
        scalar(name, result.get(name))
        scalar(f"{name}_ci95_low", low)
        scalar(f"{name}_ci95_high", high)
    for name in EVAL_SCALARS:
        scalar(name, result.get(name))
    return logged + log_videos(logger, result, step, prefix)
