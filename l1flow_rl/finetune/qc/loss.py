"""Q-chunking (QC, ColinQiyangLi/qc) on the L1 Flow policy: best-of-N chunks under a chunk critic.

The next chunk a' of the TD target is the best of N proposals of the flow's 2-NFE sampler at
s_{t+h}, picked by the ONLINE critics (their mean) and valued by the TARGET critics (``q_agg``): QC's
expected-max backup. The flow keeps its L1 Flow BC loss on the replay batches (QC's only way to
move the proposals), unless ``freeze_flow``: a frozen flow's proposals at a stored state are then
drawn once and reused (:class:`~l1flow_rl.finetune.proposal_cache.ProposalCache`), so an update costs the
critics alone instead of 256 x N flow samples.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from l1flow_rl.finetune.base import ChunkCriticLoss
from l1flow_rl.finetune.proposal_cache import ProposalCache
from l1flow_rl.finetune.qc.actor import BestOfNActor
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.networks.critic import ChunkCritic
from l1flow_rl.objectives.l1flow import L1FlowLoss
from l1flow_rl.utils.doc_examples import CRITIC, FLOW, TRAIN_STEP, TRANSITIONS, add_example

__all__ = ["QCLoss"]


@add_example(
    FLOW,
    CRITIC,
    """\
>>> from l1flow_rl import QCLoss
>>> loss_fn = QCLoss(flow, critic, num_samples=4)
""",
    TRANSITIONS,
    TRAIN_STEP,
    """\
>>> loss_fn.actor(TensorDict({"observation": torch.randn(3, 2, 5)}, [3]))["action_chunk"].shape
torch.Size([3, 8, 2])
""",
)
class QCLoss(ChunkCriticLoss):
    """Chunk-critic TD with QC's best-of-N backup, plus the flow's BC loss.

    Args:
        actor_network: the L1 Flow actor that proposes chunks (trained by the BC term).
        critic: a :class:`~l1flow_rl.networks.critic.ChunkCritic` on executed chunks [h, A].

    Keyword Args:
        num_samples: N proposals per next state (QC: 32).
        freeze_flow: keep the flow's weights as they are (no BC term, no flow parameters trained);
            the backup's proposals are then drawn once per distinct next observation and cached.
        cache_seed: mixed into the cached proposals' noise seeds (the run's seed).
        td_options: ``gamma``, ``q_agg`` and ``rl_horizon`` of :class:`~l1flow_rl.ChunkCriticLoss`.

    :attr:`actor` is the acting :class:`~l1flow_rl.BestOfNActor`: it shares the flow and the online
    critics with this loss, so acting follows training.

    Returns ``"loss_qvalue"``, ``"loss_bc"`` (absent when frozen) and detached diagnostics.
    """

    def __init__(
        self,
        actor_network: L1FlowActor,
        critic: ChunkCritic,
        *,
        num_samples: int = 32,
        freeze_flow: bool = False,
        cache_seed: int = 0,
        **td_options: Any,
    ) -> None:
        super().__init__(critic, actor_network, **td_options)
        self.__dict__["flow"] = actor_network  # the BC flow (the acting start; shared, not copied)
        self.freeze_flow = bool(freeze_flow)
        if self.freeze_flow:
            actor_network.requires_grad_(False)
            self.bc_loss = None
        else:
            # a child loss: the flow's parameters are this loss's, trained by the BC term
            self.bc_loss = L1FlowLoss(actor_network)
        # the acting module shares the flow and the online critics' tensors (not registered twice)
        self.__dict__["actor"] = BestOfNActor(
            actor_network, self.critic, num_samples=num_samples, rl_horizon=self.rl_horizon
        )
        self.proposal_cache = None
        if self.freeze_flow:
            policy = actor_network.policy
            self.proposal_cache = ProposalCache(
                lambda obs, noise: self.actor.executed(self.actor.propose(obs, noise=noise)),
                noise_shape=(int(num_samples), policy.pred_horizon, policy.action_dim),
                seed=cache_seed,
            )

    def next_value(self, td: TensorDictBase, next_obs: TensorDictBase) -> Tensor:
        if self.proposal_cache is not None:
            executed = self.proposal_cache(next_obs)  # [n, N, h, A], drawn once per observation
        else:
            executed = self.actor.executed(self.actor.propose(next_obs))
        picked = self.actor.pick_executed(next_obs, executed)  # online critics
        chosen = executed[torch.arange(executed.shape[0]), picked]
        return self.aggregate_target(self.q(next_obs, chosen, target=True))  # target critics

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        loss_q, out = self.qvalue_loss(tensordict)
        out = {"loss_qvalue": loss_q, **out}
        if self.proposal_cache is not None:  # how much of the backup the cache served (detached)
            cache = self.proposal_cache
            out["proposal_cache_size"] = torch.tensor(float(len(cache)))
            out["proposal_cache_hit_rate"] = torch.tensor(cache.hits / max(cache.hits + cache.misses, 1))
        if self.bc_loss is not None:
            bc = self.bc_loss(tensordict)
            out["loss_bc"] = bc[self.bc_loss.loss_name]
        return TensorDict(out, batch_size=[])
