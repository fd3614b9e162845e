"""The multi-modality toy (``l1flow-rl toy``)."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["ToyConfig"]


@dataclass
class ToyConfig:
    """The multi-modality demonstration (``l1flow-rl toy``); see :mod:`l1flow_rl.commands.toy`."""

    steps: int = 600  # about 90 s of CPU time for the three methods (the toy runs single-threaded)
    batch_size: int = 128
    lr: float = 1e-3
    samples: int = 512
    seed: int = 0
    modes: str = "opposite_sines"  # opposite_sines (2) | nested_amplitudes (4) | phase_shifts (8)
    methods: list[str] = field(default_factory=lambda: ["l1flow", "flow_matching", "regression"])
