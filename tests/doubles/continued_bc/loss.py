"""The continued-BC loss: the flow's L1 Flow loss, weighted, as a TorchRL ``LossModule``."""

from __future__ import annotations

from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from l1flow_rl import L1FlowActor, L1FlowLoss

__all__ = ["ContinuedBCLoss"]


class ContinuedBCLoss(LossModule):
    """``weight`` times the L1 Flow loss of ``actor_network`` (trained and acting: shared, not copied).
    Returns ``"loss_bc"`` and the L1 Flow loss's detached diagnostics."""

    def __init__(self, actor_network: L1FlowActor, *, weight: float = 1.0) -> None:
        super().__init__()
        self.bc_loss = L1FlowLoss(actor_network)  # a child loss: the flow's parameters are this loss's
        self.__dict__["actor"] = actor_network
        self.__dict__["flow"] = actor_network
        self.rl_horizon = actor_network.policy.action_steps
        self.weight = float(weight)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass  # no critic

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        out = self.bc_loss(tensordict)
        loss = out.pop(self.bc_loss.loss_name)
        detached = {k: v.detach() for k, v in out.items()}
        return TensorDict({"loss_bc": self.weight * loss, **detached}, batch_size=[])
