"""flow-Q on chunks: the L1 Flow policy's 2-NFE sampler is the actor, trained up the chunk critics.

* The actor is the flow passed in (a trainable copy of the BC flow, so at step 0 it samples exactly
  the BC policy's chunk for any noise); a frozen copy of it made here is the teacher.
* The actor minimises ``alpha * ||actor(s, z) - teacher(s, z)||^2 - lambda * Q(s, actor(s, z))``, both
  chunks sampled by the flows' own 2-NFE sampler from the same noise z; the gradient goes through both
  network calls of the actor's sampler and never reaches the teacher (sampled under no_grad) or the
  critics (their parameters detached). With ``bc_on_data`` the anchor is the flow's L1 Flow loss on the
  batch's chunks instead.
* ``lambda = 1 / max(mean|Q|, q_scale_floor)`` (detached) with ``normalize_q_loss`` (FQL's
  normalisation, floored: see :class:`~l1flow_rl.finetune.flowq.settings.FlowQSettings`), Q the
  critics' mean.
* The TD target's next chunk is the actor's own 2-NFE sample at s_{t+h}.

Nothing is clipped: the chunk the critics value is the one the flow executes, as the BC policy acts
(the environment applies its own bounds), so the critics value the actions they were trained on.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from l1flow_rl.finetune.base import ChunkCriticLoss
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.modules.policy import ChunkPolicy
from l1flow_rl.networks.critic import ChunkCritic
from l1flow_rl.objectives.l1flow import L1FlowLoss
from l1flow_rl.utils.doc_examples import CRITIC, FLOW, TRAIN_STEP, TRANSITIONS, add_example

__all__ = ["FlowQLoss"]


def sample(policy: ChunkPolicy, obs: TensorDictBase, z: Tensor) -> Tensor:
    """The policy's normalised chunk [N, H, A] from noise ``z`` at read observations [N, To], through
    its own sampler (differentiable: both network calls of the 2-NFE sampler are in the graph)."""
    cond = policy.encode(obs)
    return policy.sampler(lambda x, t: policy.denoise(x, t, cond), z.to(cond))


@add_example(
    FLOW,
    CRITIC,
    """\
>>> from l1flow_rl import FlowQLoss
>>> loss_fn = FlowQLoss(flow, critic, alpha=10.0)
>>> z, obs = torch.randn(3, 16, 2), torch.randn(3, 2, 5)
>>> bool((flow.policy.sample_chunk(obs, noise=z) == loss_fn.teacher.policy.sample_chunk(obs, noise=z)).all())
True
""",
    TRANSITIONS,
    TRAIN_STEP,
    """\
>>> sorted(k for k in out.keys() if k.startswith("loss_"))
['loss_actor', 'loss_qvalue']
>>> loss_fn.actor is flow, all(not p.requires_grad for p in loss_fn.teacher.parameters())
(True, True)
""",
)
class FlowQLoss(ChunkCriticLoss):
    """flow-Q: chunk-critic TD and the 2-NFE flow's anchored climb of the critics.

    Args:
        actor_network: the L1 Flow actor that is trained and acts (pass a copy of the BC flow; a
            frozen copy of it is made here as the teacher).
        critic: a :class:`~l1flow_rl.networks.critic.ChunkCritic` on executed chunks [h, A].

    Keyword Args:
        alpha: weight of the anchor term.
        normalize_q_loss: scale the Q term by ``1 / max(mean|Q|, q_scale_floor)`` (detached).
        q_scale_floor: the floor of that scale (caps lambda at ``1 / q_scale_floor``).
        bc_on_data: anchor with the flow's L1 Flow loss on the batch's chunks instead of the distance
            to the teacher's chunk.
        td_options: ``gamma``, ``q_agg``, ``rl_horizon`` and ``target_critics`` of
            :class:`~l1flow_rl.ChunkCriticLoss`.

    :attr:`actor` is the trained flow; :attr:`flow`, the BC start that acts during the warm-up, is the
    teacher. Returns ``"loss_qvalue"``, ``"loss_actor"`` and detached ``"q_actor_mean"``,
    ``"anchor_loss"`` (the anchor term before ``alpha``), ``"teacher_distance"`` (mean squared
    distance of the actor's chunk to the teacher's), ``"lambda"`` and the critic diagnostics.
    """

    def __init__(
        self,
        actor_network: L1FlowActor,
        critic: ChunkCritic,
        *,
        alpha: float = 10.0,
        normalize_q_loss: bool = True,
        q_scale_floor: float = 0.1,
        bc_on_data: bool = False,
        **td_options: Any,
    ) -> None:
        if alpha < 0:
            raise ValueError(f"alpha must be >= 0, got {alpha}")
        if q_scale_floor <= 0:
            raise ValueError(f"q_scale_floor must be > 0, got {q_scale_floor}")
        if not isinstance(actor_network, L1FlowActor):
            raise TypeError(f"actor_network must be an L1FlowActor, got {type(actor_network).__name__}")
        super().__init__(critic, actor_network, **td_options)
        # registered (moves with the loss, saved with it) but frozen: never in the optimiser
        self.teacher = copy.deepcopy(actor_network).requires_grad_(False)
        self.actor_network = actor_network  # its parameters are this loss's, trained by loss_actor
        self.bc_loss = L1FlowLoss(actor_network) if bc_on_data else None
        self.__dict__["flow"] = self.teacher  # the BC start (acts during the warm-up)
        self.alpha, self.normalize_q_loss = float(alpha), bool(normalize_q_loss)
        self.q_scale_floor = float(q_scale_floor)

    @property
    def actor(self) -> L1FlowActor:
        """The acting module: the trained flow."""
        return self.actor_network

    def _noise(self, n: int) -> Tensor:
        policy = self.actor_network.policy
        scale = policy.action_normalizer.scale
        return torch.randn(n, policy.pred_horizon, policy.action_dim, dtype=policy.dtype, device=scale.device)

    def _env_executed(self, x: Tensor) -> Tensor:
        return self.actor_network.policy.action_normalizer.unnormalize(self.executed(x))

    def next_value(self, td: TensorDictBase, next_obs: TensorDictBase) -> Tensor:
        x = sample(self.actor_network.policy, next_obs, self._noise(next_obs.shape[0]))
        return self.aggregate_target(self.q(next_obs, self._env_executed(x), target=True))

    def q_weight(self, q: Tensor) -> Tensor:
        """lambda (detached): ``1 / max(mean|Q|, q_scale_floor)``, or 1 without normalisation."""
        if not self.normalize_q_loss:
            return q.new_ones(())
        return 1.0 / q.abs().mean().detach().clamp_min(self.q_scale_floor)

    def actor_loss(self, td: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        obs = self.read_observation(td, self.tensor_keys.observation)
        z = self._noise(obs.shape[0])
        x = sample(self.actor_network.policy, obs, z)  # the gradient goes through both NFEs
        with torch.no_grad():
            teacher = sample(self.teacher.policy, obs, z)
        distance = (x - teacher).square().mean()
        anchor = self.bc_loss(td)[self.bc_loss.loss_name] if self.bc_loss is not None else distance
        q = self.q(obs, self._env_executed(x), detach=True).mean(-1)
        lam = self.q_weight(q)
        loss = self.alpha * anchor - lam * q.mean()
        return loss, {
            "q_actor_mean": q.mean().detach(),
            "anchor_loss": anchor.detach(),
            "teacher_distance": distance.detach(),
            "lambda": lam.detach(),
        }

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        loss_q, out = self.qvalue_loss(tensordict)
        loss_actor, actor_out = self.actor_loss(tensordict)
        return TensorDict(
            {"loss_qvalue": loss_q, "loss_actor": loss_actor, **out, **actor_out}, batch_size=[]
        )
