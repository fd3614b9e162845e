"""flow-Q's settings block, ``finetune.flowq``."""

from __future__ import annotations

from dataclasses import dataclass

from l1flow_rl.config.ranges import bounded

__all__ = ["FlowQSettings"]


@dataclass
class FlowQSettings:
    # weight of the anchor ||actor(s, z) - teacher(s, z)||^2; FQL's alpha for a normalised Q term
    alpha: float = bounded(10.0, ge=0)
    normalize_q_loss: bool = True  # FQL: lambda = 1 / mean|Q| (detached), with the floor below
    # lambda = 1 / max(mean|Q|, floor): FQL's 1 / mean|Q| grows without bound while the critics sit near
    # 0 (sparse success rewards before any success is valued), where their gradient is noise; the floor
    # caps lambda at 10, the anchor's alpha, and leaves FQL's normalisation as is once values reach a
    # tenth of a success reward
    q_scale_floor: float = bounded(0.1, gt=0)
    # anchor on the batch's chunks (the flow's L1 Flow loss) instead of on the frozen BC flow's chunk
    bc_on_data: bool = False
