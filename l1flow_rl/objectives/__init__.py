"""TorchRL losses for chunk policies, one per file: L1 Flow and its behaviour-cloning baselines, on one
shared base (:mod:`.chunk_loss`), registered by name for ``policy.loss`` (:mod:`.registry`). The
fine-tuning losses live with their algorithms, in :mod:`l1flow_rl.finetune`."""

from l1flow_rl.objectives.chunk_loss import ChunkLossBase
from l1flow_rl.objectives.consistency import ConsistencyLoss
from l1flow_rl.objectives.diffusion import DiffusionLoss
from l1flow_rl.objectives.edm import EDMLoss
from l1flow_rl.objectives.flow_matching import FlowMatchingLoss
from l1flow_rl.objectives.l1flow import L1FlowLoss
from l1flow_rl.objectives.onedp_d import OneDPDLoss
from l1flow_rl.objectives.onedp_s import OneDPSLoss
from l1flow_rl.objectives.registry import get_loss, loss_names, register_loss
from l1flow_rl.objectives.regression import RegressionLoss

__all__ = [
    "ChunkLossBase",
    "ConsistencyLoss",
    "DiffusionLoss",
    "EDMLoss",
    "FlowMatchingLoss",
    "L1FlowLoss",
    "OneDPDLoss",
    "OneDPSLoss",
    "RegressionLoss",
    "get_loss",
    "loss_names",
    "register_loss",
]
