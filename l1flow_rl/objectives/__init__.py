"""TorchRL losses for chunk policies: L1 Flow and its baselines, and flow Q-learning; one per file.
The behaviour-cloning losses are registered by name for ``policy.loss`` (:mod:`.registry`)."""

from l1flow_rl.objectives.chunk_loss import ChunkLossBase
from l1flow_rl.objectives.diffusion import DiffusionLoss
from l1flow_rl.objectives.flow_matching import FlowMatchingLoss
from l1flow_rl.objectives.flow_q import FlowQLoss
from l1flow_rl.objectives.l1flow import L1FlowLoss
from l1flow_rl.objectives.registry import get_loss, loss_names, register_loss
from l1flow_rl.objectives.regression import RegressionLoss

__all__ = [
    "ChunkLossBase",
    "DiffusionLoss",
    "FlowMatchingLoss",
    "FlowQLoss",
    "L1FlowLoss",
    "RegressionLoss",
    "get_loss",
    "loss_names",
    "register_loss",
]
