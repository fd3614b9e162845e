"""DSRL-NA as a fine-tuning algorithm: its loss built from the ``finetune`` config, and what the loop
needs."""

from __future__ import annotations

from omegaconf import DictConfig

from l1flow_rl.finetune.dsrl.algorithm import SteeringAlgorithm
from l1flow_rl.finetune.dsrl_na.loss import DSRLNALoss
from l1flow_rl.finetune.dsrl_na.settings import DSRLNASettings
from l1flow_rl.modules.actor import L1FlowActor

__all__ = ["ALGORITHM", "DSRLNA"]


class DSRLNA(SteeringAlgorithm):
    """SAC over the flow's noise on a noise critic distilled from an action critic
    (:class:`~l1flow_rl.DSRLNALoss`)."""

    name = "dsrl_na"
    settings = DSRLNASettings
    # its action critic values the executed actions of any window, demonstrations included: it stores
    # nothing beyond the core entries and reads every window
    online_keys = ()

    def build(self, flow: L1FlowActor, cfg: DictConfig, *, seed: int = 0) -> DSRLNALoss:
        s = self.settings_of(cfg)
        steer = self.steering_actor(flow, s)
        return DSRLNALoss(
            steer,
            self.critic(flow, cfg, self.executed_shape(flow, cfg)),
            self.critic(flow, cfg, steer.noise_policy.noise_shape, normalize_input=False),
            target_entropy=float(s.target_entropy),
            init_alpha=float(s.init_alpha),
            distill_samples=int(s.distill_samples),
            cache_seed=seed,
            **self.td_options(cfg),
        )


ALGORITHM = DSRLNA()
