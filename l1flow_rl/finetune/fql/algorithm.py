"""FQL as a fine-tuning algorithm: its loss built from the ``finetune`` config, and what the loop needs."""

from __future__ import annotations

from omegaconf import DictConfig

from l1flow_rl.finetune.base import ChunkCriticAlgorithm
from l1flow_rl.finetune.fql.actor import OneStepActor
from l1flow_rl.finetune.fql.loss import FQLLoss
from l1flow_rl.finetune.fql.settings import FQLSettings
from l1flow_rl.modules.actor import L1FlowActor

__all__ = ["ALGORITHM", "FQL"]


class FQL(ChunkCriticAlgorithm):
    """A one-step actor distilled from the flow that climbs the critics (:class:`~l1flow_rl.FQLLoss`);
    its EMA, where set, averages that actor."""

    name = "fql"
    settings = FQLSettings

    def build(self, flow: L1FlowActor, cfg: DictConfig, *, seed: int = 0) -> FQLLoss:
        s = self.settings_of(cfg)
        mu = OneStepActor.from_flow(flow, hidden_dims=tuple(s.actor_hidden_dims))
        return FQLLoss(
            mu,
            flow,
            self.critic(flow, cfg, self.executed_shape(flow, cfg)),
            alpha=float(s.alpha),
            normalize_q_loss=bool(s.normalize_q_loss),
            **self.td_options(cfg),
        )


ALGORITHM = FQL()
