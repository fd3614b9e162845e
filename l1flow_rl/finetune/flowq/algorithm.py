"""flow-Q as a fine-tuning algorithm: its loss built from the ``finetune`` config, and what the loop
needs."""

from __future__ import annotations

from omegaconf import DictConfig

from l1flow_rl.finetune.base import ChunkCriticAlgorithm
from l1flow_rl.finetune.flowq.loss import FlowQLoss
from l1flow_rl.finetune.flowq.settings import FlowQSettings
from l1flow_rl.modules.actor import L1FlowActor

__all__ = ["ALGORITHM", "FlowQ"]


class FlowQ(ChunkCriticAlgorithm):
    """The BC flow's 2-NFE sampler trained up the critics, anchored to the frozen BC flow
    (:class:`~l1flow_rl.FlowQLoss`). The trained flow acts; its EMA, where set, goes on from the BC
    run's counter."""

    name = "flowq"
    actor_is_start = True
    settings = FlowQSettings

    def build(self, flow: L1FlowActor, cfg: DictConfig, *, seed: int = 0) -> FlowQLoss:
        s = self.settings_of(cfg)
        return FlowQLoss(
            flow,
            self.critic(flow, cfg, self.executed_shape(flow, cfg)),
            alpha=float(s.alpha),
            normalize_q_loss=bool(s.normalize_q_loss),
            q_scale_floor=float(s.q_scale_floor),
            bc_on_data=bool(s.bc_on_data),
            **self.td_options(cfg),
        )

    def with_flow(self, loss: FlowQLoss, flow: L1FlowActor) -> L1FlowActor:
        return flow  # the trained flow acts: with finetune.ema_power its average does


ALGORITHM = FlowQ()
