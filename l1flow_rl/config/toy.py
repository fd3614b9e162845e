"""The multi-modality toy (``l1flow-rl toy``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from l1flow_rl.config.ranges import bounded

__all__ = ["ToyConfig"]


@dataclass
class ToyConfig:
    """The multi-modality demonstration (``l1flow-rl toy``); see :mod:`l1flow_rl.commands.toy`."""

    # about 90 s of CPU time for the three methods (the toy runs single-threaded)
    steps: int = bounded(600, ge=1)
    batch_size: int = bounded(128, ge=1)
    lr: float = bounded(1e-3, gt=0)
    samples: int = bounded(512, ge=1)
    seed: int = bounded(0, ge=0, lt=2**32)
    modes: str = "opposite_sines"  # opposite_sines (2) | nested_amplitudes (4) | phase_shifts (8)
    methods: list[str] = field(default_factory=lambda: ["l1flow", "flow_matching", "regression"])
