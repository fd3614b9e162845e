"""The train group (``configs/train/*.yaml``): optimisation, checkpoints, logging."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["LOGGERS", "TrainConfig"]

#: TorchRL loggers a run can write to (``train.logger``)
LOGGERS = ("csv", "tensorboard", "wandb")


@dataclass
class TrainConfig:
    steps: int = 3000
    batch_size: int = 256
    lr: float = 1e-4
    betas: list[float] = field(default_factory=lambda: [0.95, 0.999])
    weight_decay: float = 1e-6
    warmup_steps: int = 500
    ema_power: float = 0.75
    grad_clip: float = 0.0  # 0 disables
    amp: bool = False
    compile: bool = False
    checkpoint_every: int = 1000
    log_every: int = 50
    eval_every: int = 0  # 0: evaluate only at the end
    logger: str = "csv"  # LOGGERS: csv | tensorboard | wandb
    project: str = "l1flow-rl"  # W&B project
    group: str | None = None  # W&B group (e.g. one per sweep)
    # The logger's run name; None: the run directory's name on W&B, "train" (its log folder) otherwise.
    run_name: str | None = None
    prefetch: int = 0  # batches sampled ahead by threads; 0 keeps resume bit-exact
