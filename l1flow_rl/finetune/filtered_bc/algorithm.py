"""Filtered BC as a fine-tuning algorithm: its loss built from the ``finetune`` config, and what the
loop needs (no critic, hence no target networks)."""

from __future__ import annotations

from omegaconf import DictConfig

from l1flow_rl.finetune.base import FinetuneAlgorithm
from l1flow_rl.finetune.filtered_bc.loss import FilteredBCLoss
from l1flow_rl.finetune.filtered_bc.settings import FilteredBCSettings
from l1flow_rl.modules.actor import L1FlowActor

__all__ = ["ALGORITHM", "FilteredBC"]


class FilteredBC(FinetuneAlgorithm):
    """The flow's own L1 Flow loss on successful episodes (:class:`~l1flow_rl.FilteredBCLoss`)."""

    name = "filtered_bc"
    settings = FilteredBCSettings
    successful_episodes_only = True

    def build(self, flow: L1FlowActor, cfg: DictConfig, *, seed: int = 0) -> FilteredBCLoss:
        return FilteredBCLoss(
            flow,
            rl_horizon=int(cfg.rl_horizon) or None,
            mask_padding=bool(self.settings_of(cfg).mask_padding),
        )

    def with_flow(self, loss: FilteredBCLoss, flow: L1FlowActor) -> L1FlowActor:
        return flow  # the flow is the acting module


ALGORITHM = FilteredBC()
