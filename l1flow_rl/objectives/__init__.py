"""TorchRL losses for chunk policies, one per file: L1 Flow and its baselines (behaviour cloning), the
fine-tuning losses QC, FQL, DSRL and DSRL-NA on one shared chunk-critic TD loss, and filtered BC (no
critic). The behaviour-cloning losses are registered by name for ``policy.loss`` (:mod:`.registry`)."""

from l1flow_rl.objectives.chunk_critic import ChunkCriticLoss
from l1flow_rl.objectives.chunk_loss import ChunkLossBase
from l1flow_rl.objectives.consistency import ConsistencyLoss
from l1flow_rl.objectives.diffusion import DiffusionLoss
from l1flow_rl.objectives.dsrl import DSRLLoss
from l1flow_rl.objectives.dsrl_na import DSRLNALoss
from l1flow_rl.objectives.edm import EDMLoss
from l1flow_rl.objectives.filtered_bc import FilteredBCLoss
from l1flow_rl.objectives.flow_matching import FlowMatchingLoss
from l1flow_rl.objectives.fql import FQLLoss
from l1flow_rl.objectives.l1flow import L1FlowLoss
from l1flow_rl.objectives.onedp_d import OneDPDLoss
from l1flow_rl.objectives.onedp_s import OneDPSLoss
from l1flow_rl.objectives.qc import QCLoss
from l1flow_rl.objectives.registry import get_loss, loss_names, register_loss
from l1flow_rl.objectives.regression import RegressionLoss

__all__ = [
    "ChunkCriticLoss",
    "ChunkLossBase",
    "ConsistencyLoss",
    "DSRLLoss",
    "DSRLNALoss",
    "DiffusionLoss",
    "EDMLoss",
    "FQLLoss",
    "FilteredBCLoss",
    "FlowMatchingLoss",
    "L1FlowLoss",
    "OneDPDLoss",
    "OneDPSLoss",
    "QCLoss",
    "RegressionLoss",
    "get_loss",
    "loss_names",
    "register_loss",
]
