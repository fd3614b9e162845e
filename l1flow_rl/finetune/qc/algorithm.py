"""QC as a fine-tuning algorithm: its loss built from the ``finetune`` config, and what the loop needs."""

from __future__ import annotations

from omegaconf import DictConfig

from l1flow_rl.finetune.base import ChunkCriticAlgorithm
from l1flow_rl.finetune.qc.actor import BestOfNActor
from l1flow_rl.finetune.qc.loss import QCLoss
from l1flow_rl.finetune.qc.settings import QCSettings
from l1flow_rl.modules.actor import L1FlowActor

__all__ = ["ALGORITHM", "QC"]


class QC(ChunkCriticAlgorithm):
    """Best-of-N proposals of the flow, picked by the online critics (:class:`~l1flow_rl.QCLoss`)."""

    name = "qc"
    actor_is_start = True
    settings = QCSettings

    def build(self, flow: L1FlowActor, cfg: DictConfig, *, seed: int = 0) -> QCLoss:
        s = self.settings_of(cfg)
        return QCLoss(
            flow,
            self.critic(flow, cfg, self.executed_shape(flow, cfg)),
            num_samples=int(s.num_samples),
            freeze_flow=bool(s.freeze_flow),
            cache_seed=seed,
            **self.td_options(cfg),
        )

    def with_flow(self, loss: QCLoss, flow: L1FlowActor) -> BestOfNActor:
        # another flow proposes, the online critics still pick
        return BestOfNActor(flow, loss.critic, num_samples=loss.actor.num_samples, rl_horizon=loss.rl_horizon)


ALGORITHM = QC()
