"""The block ``finetune.continued_bc``."""

from __future__ import annotations

from dataclasses import dataclass

from l1flow_rl.config.ranges import bounded

__all__ = ["ContinuedBCSettings"]


@dataclass
class ContinuedBCSettings:
    weight: float = bounded(1.0, gt=0)  # the BC loss's weight (only to show a checked range)
