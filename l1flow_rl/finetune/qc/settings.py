"""QC's settings block, ``finetune.qc`` (defaults: ColinQiyangLi/qc)."""

from __future__ import annotations

from dataclasses import dataclass

from l1flow_rl.config.ranges import bounded

__all__ = ["QCSettings"]


@dataclass
class QCSettings:
    num_samples: int = bounded(32, ge=1)  # QC: best of 32 proposals, for acting and for the backup
    freeze_flow: bool = False  # QC trains the flow with its BC loss on the replay buffer
