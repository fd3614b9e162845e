"""L1 Flow: two-step sample-prediction flow-matching policies for TorchRL.

Quick use::

    from l1flow_rl import L1FlowActor, L1FlowLoss
    actor = L1FlowActor.for_state(obs_dim=D, action_dim=A, down_dims=(64, 128, 256))
    loss_fn = L1FlowLoss(actor)
"""

from l1flow_rl.evaluation import evaluate
from l1flow_rl.finetune.base import ChunkCriticLoss
from l1flow_rl.finetune.dsrl.actor import NoiseActor
from l1flow_rl.finetune.dsrl.loss import DSRLLoss
from l1flow_rl.finetune.dsrl_na.loss import DSRLNALoss
from l1flow_rl.finetune.filtered_bc.loss import FilteredBCLoss
from l1flow_rl.finetune.flowq.loss import FlowQLoss
from l1flow_rl.finetune.fql.actor import OneStepActor
from l1flow_rl.finetune.fql.loss import FQLLoss
from l1flow_rl.finetune.qc.actor import BestOfNActor
from l1flow_rl.finetune.qc.loss import QCLoss
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.modules.ema import dp_ema_decay, make_ema
from l1flow_rl.modules.normalizer import Normalizer, NormalizerDict
from l1flow_rl.modules.policy import ChunkPolicy
from l1flow_rl.objectives import (
    ConsistencyLoss,
    DiffusionLoss,
    EDMLoss,
    FlowMatchingLoss,
    L1FlowLoss,
    OneDPDLoss,
    OneDPSLoss,
    RegressionLoss,
)

__all__ = [
    "BestOfNActor",
    "ChunkCriticLoss",
    "ChunkPolicy",
    "ConsistencyLoss",
    "DSRLLoss",
    "DSRLNALoss",
    "DiffusionLoss",
    "EDMLoss",
    "FQLLoss",
    "FilteredBCLoss",
    "FlowMatchingLoss",
    "FlowQLoss",
    "L1FlowActor",
    "L1FlowLoss",
    "NoiseActor",
    "Normalizer",
    "NormalizerDict",
    "OneDPDLoss",
    "OneDPSLoss",
    "OneStepActor",
    "QCLoss",
    "RegressionLoss",
    "dp_ema_decay",
    "evaluate",
    "make_ema",
]
