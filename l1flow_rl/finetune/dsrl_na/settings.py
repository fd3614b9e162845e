"""DSRL-NA's settings block, ``finetune.dsrl_na``: DSRL's, plus the distillation's noises."""

from __future__ import annotations

from dataclasses import dataclass

from l1flow_rl.config.ranges import bounded
from l1flow_rl.finetune.dsrl.settings import DSRLSettings

__all__ = ["DSRLNASettings"]


@dataclass
class DSRLNASettings(DSRLSettings):
    # noises per observation the noise critic is fitted on, decoded once (the flow is frozen; DSRL-NA
    # draws one fresh noise per state at every distillation step, a flow call per update on 2 cores)
    distill_samples: int = bounded(4, ge=1)
