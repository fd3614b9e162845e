"""``ALGORITHM``: what ``l1flow-rl finetune`` asks of continued BC."""

from __future__ import annotations

from omegaconf import DictConfig

from l1flow_rl import L1FlowActor
from l1flow_rl.finetune.base import FinetuneAlgorithm

from .loss import ContinuedBCLoss
from .settings import ContinuedBCSettings

__all__ = ["ALGORITHM", "ContinuedBC"]


class ContinuedBC(FinetuneAlgorithm):
    name = "continued_bc"  # its block: finetune.continued_bc
    settings = ContinuedBCSettings

    def build(self, flow: L1FlowActor, cfg: DictConfig, *, seed: int = 0) -> ContinuedBCLoss:
        return ContinuedBCLoss(flow, weight=float(self.settings_of(cfg).weight))

    def with_flow(self, loss: ContinuedBCLoss, flow: L1FlowActor) -> L1FlowActor:
        return flow  # the flow acts: with finetune.ema_power its average does


ALGORITHM = ContinuedBC()
