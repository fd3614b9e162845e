"""DSRL as a fine-tuning algorithm: its loss built from the ``finetune`` config, and what the loop needs."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from l1flow_rl.finetune.base import ChunkCriticAlgorithm
from l1flow_rl.finetune.dsrl.actor import NoiseActor
from l1flow_rl.finetune.dsrl.loss import DSRLLoss
from l1flow_rl.finetune.dsrl.settings import DSRLSettings
from l1flow_rl.modules.actor import L1FlowActor

__all__ = ["ALGORITHM", "DSRL", "SteeringAlgorithm"]


class SteeringAlgorithm(ChunkCriticAlgorithm):
    """An algorithm that acts by steering the frozen flow's input noise (:class:`~l1flow_rl.NoiseActor`):
    its warm-up acts through the same wrapper with the prior's noise, so the online buffer stores the
    noise of every chunk and the wrapper's step count (1 where a chunk starts)."""

    online_keys = ("noise", "counter")

    def steering_actor(self, flow: L1FlowActor, settings: DictConfig) -> NoiseActor:
        return NoiseActor.from_flow(
            flow, bound=float(settings.noise_bound), hidden_dims=tuple(settings.actor_hidden_dims)
        )

    def start_actor(self, loss: DSRLLoss) -> NoiseActor:
        return loss.actor.prior()

    def buffer_options(self, cfg: DictConfig | None = None) -> dict[str, Any]:
        options = super().buffer_options(cfg)
        if self.settings_of(cfg or {}).discount_per_chunk:  # a chunk's rewards are one step's, summed
            options["return_discount"] = 1.0
        return options

    def td_options(self, cfg: DictConfig) -> dict[str, Any]:
        return {
            **super().td_options(cfg),
            "per_chunk_discount": bool(self.settings_of(cfg).discount_per_chunk),
        }


class DSRL(SteeringAlgorithm):
    """SAC over the flow's noise, valued by a critic of the noise (:class:`~l1flow_rl.DSRLLoss`)."""

    name = "dsrl"
    settings = DSRLSettings
    # sampling every step gave 1 valid window in action_steps: the noise describes the actions from
    # a chunk's start on
    online_anchor_key = "counter"
    uses_offline_data = False  # the demonstrations carry no steering noise

    def build(self, flow: L1FlowActor, cfg: DictConfig, *, seed: int = 0) -> DSRLLoss:
        s = self.settings_of(cfg)
        steer = self.steering_actor(flow, s)
        return DSRLLoss(
            steer,
            self.critic(flow, cfg, steer.noise_policy.noise_shape, normalize_input=False),
            target_entropy=float(s.target_entropy),
            init_alpha=float(s.init_alpha),
            **self.td_options(cfg),
        )


ALGORITHM = DSRL()
