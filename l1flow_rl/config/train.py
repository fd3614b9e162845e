"""The train group (``configs/train/*.yaml``): optimisation, checkpoints, logging."""

from __future__ import annotations

from dataclasses import dataclass

from l1flow_rl.config.ranges import bounded

__all__ = ["LOGGERS", "TrainConfig"]

#: TorchRL loggers a run can write to (``train.logger``)
LOGGERS = ("csv", "tensorboard", "wandb")


@dataclass
class TrainConfig:
    steps: int = bounded(3000, ge=1)
    batch_size: int = bounded(256, ge=1)
    lr: float = bounded(1e-4, gt=0)
    betas: list[float] = bounded(lambda: [0.95, 0.999], ge=0, lt=1, each=True)  # Adam's two betas
    weight_decay: float = bounded(1e-6, ge=0)
    warmup_steps: int = bounded(500, ge=0)
    # Diffusion Policy's EMA schedule: decay 1 - (1 + step) ** -ema_power
    ema_power: float = bounded(0.75, ge=0, zero="no averaging: the raw weights")
    grad_clip: float = bounded(0.0, ge=0, zero="no clipping")
    amp: bool = False
    compile: bool = False
    checkpoint_every: int = bounded(1000, ge=0, zero="only at the end")
    log_every: int = bounded(50, ge=0, zero="only at the end")
    eval_every: int = bounded(0, ge=0, zero="evaluate only at the end")
    logger: str = "csv"  # LOGGERS: csv | tensorboard | wandb
    project: str = "l1flow-rl"  # W&B project
    group: str | None = None  # W&B group (e.g. one per sweep)
    # The logger's run name; None: the run directory's name on W&B, "train" (its log folder) otherwise.
    run_name: str | None = None
    # batches sampled ahead by threads
    prefetch: int = bounded(0, ge=0, zero="none, which keeps resume bit-exact")
