"""FQL's settings block, ``finetune.fql`` (defaults: seohongpark/fql)."""

from __future__ import annotations

from dataclasses import dataclass

from l1flow_rl.config.ranges import bounded

__all__ = ["FQLSettings"]


@dataclass
class FQLSettings:
    # FQL's README: alpha in {0.03, ..., 10} once Q is normalised; 10 is TorchRL 0.15's FQLLoss default
    alpha: float = bounded(10.0, ge=0)
    normalize_q_loss: bool = True  # FQL: lambda = 1 / mean|Q| (detached)
    # FQL: 4 x 512
    actor_hidden_dims: list[int] = bounded(lambda: [512, 512, 512, 512], ge=1, each=True)
