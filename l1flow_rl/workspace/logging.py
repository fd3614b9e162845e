"""The run's TorchRL logger (CSV, TensorBoard or W&B) under ``run_dir/logs``."""

from __future__ import annotations

from pathlib import Path

__all__ = ["make_logger"]


def make_logger(kind: str, run_dir: Path, state: dict | None):
    from torchrl.record.loggers import get_logger

    if kind not in ("csv", "tensorboard", "wandb"):
        raise ValueError(f"train.logger={kind!r}; expected csv, tensorboard or wandb")
    return get_logger(kind, logger_name=str(run_dir / "logs"), experiment_name="train", state_dict=state)
