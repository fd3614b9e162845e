"""Filtered behaviour cloning on the L1 Flow policy: its own L1 Flow loss on the demonstrations and on
the online episodes that ended in success, with no critic.

The control that separates "online data" from "TD": the policy improves only by imitating the
successes it collects (the reward enters as a filter, not through a value). Batches mix demonstrations
and successful online windows as the other algorithms' do (``online.offline_fraction``).
"""

from __future__ import annotations

from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.objectives.l1flow import L1FlowLoss

__all__ = ["FilteredBCLoss"]


class FilteredBCLoss(LossModule):
    """The flow's L1 Flow loss on the windows it is given; both buffers keep only the windows of
    episodes that ended in success (its algorithm's ``successful_episodes_only``): a mixed-quality
    demonstration set's failed episodes are filtered out like the failed online ones.

    Args:
        actor_network: the :class:`~l1flow_rl.L1FlowActor` that acts and is trained (shared, not copied).

    Keyword Args:
        rl_horizon: the executed actions per chunk, read by the replay buffers' windows (default: the
            policy's ``action_steps``); nothing here depends on it.
        mask_padding: leave the steps ``action_is_pad`` flags out of the loss (see
            :class:`~l1flow_rl.objectives.chunk_loss.ChunkLossBase`); default False, as BC trains.

    Returns ``"loss_bc"`` and the L1 Flow loss's detached diagnostics.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from l1flow_rl import FilteredBCLoss, L1FlowActor
        >>> flow = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
        >>> loss_fn = FilteredBCLoss(flow)
        >>> td = TensorDict({"observation": torch.randn(4, 2, 5),
        ...                  "action_chunk": torch.rand(4, 16, 2) * 2 - 1}, batch_size=[4])
        >>> loss_fn(td)["loss_bc"].backward()
        >>> loss_fn.actor is flow
        True
    """

    def __init__(
        self, actor_network: L1FlowActor, *, rl_horizon: int | None = None, mask_padding: bool = False
    ) -> None:
        if not isinstance(actor_network, L1FlowActor):
            raise TypeError(f"actor_network must be an L1FlowActor, got {type(actor_network).__name__}")
        super().__init__()
        # a child loss: the flow's parameters are this loss's, trained by the BC term
        self.bc_loss = L1FlowLoss(actor_network, mask_padding=mask_padding)
        self.__dict__["actor"] = actor_network  # acting follows training (shared weights)
        self.__dict__["flow"] = actor_network
        self.rl_horizon = int(rl_horizon or actor_network.policy.action_steps)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass  # no value estimator: no critic

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        out = self.bc_loss(tensordict)
        loss = out.pop(self.bc_loss.loss_name)
        return TensorDict({"loss_bc": loss, **{k: v.detach() for k, v in out.items()}}, batch_size=[])
