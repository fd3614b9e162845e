"""Flow Q-learning (FQL, seohongpark/fql) on chunks, with the L1 Flow policy as the BC flow.

* The BC flow keeps training with its L1 Flow loss on the replay batches.
* The one-step policy mu(s, z) (:class:`~l1flow_rl.OneStepActor`, trained from scratch) minimises
  ``alpha * ||mu(s, z) - flow(s, z)||^2 - lambda * Q(s, clip(mu(s, z)))``: the teacher's chunk is its
  2-NFE sample from the same noise z, under no_grad and clipped to the action range; mu's raw output
  is distilled and only what the critics value is clipped (seohongpark/fql), so a unit past a bound
  still feels the distillation; ``lambda = 1 / mean|Q|`` (detached) with ``normalize_q_loss``, Q the
  critics' mean.
* The TD target's next chunk is mu's at s_{t+h}, clipped as it would be executed.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from l1flow_rl.finetune.base import ChunkCriticLoss
from l1flow_rl.finetune.fql.actor import OneStepActor, OneStepPolicy
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.modules.normalizer import clip_actions
from l1flow_rl.networks.critic import ChunkCritic
from l1flow_rl.objectives.l1flow import L1FlowLoss
from l1flow_rl.utils.doc_examples import CRITIC, FLOW, TRAIN_STEP, TRANSITIONS, add_example

__all__ = ["FQLLoss"]


@add_example(
    FLOW,
    CRITIC,
    """\
>>> from l1flow_rl import FQLLoss, OneStepActor
>>> mu = OneStepActor.from_flow(flow, hidden_dims=(64,))
>>> loss_fn = FQLLoss(mu, flow, critic, alpha=10.0)
""",
    TRANSITIONS,
    TRAIN_STEP,
    """\
>>> sorted(k for k in out.keys() if k.startswith("loss_"))
['loss_actor', 'loss_bc', 'loss_qvalue']
""",
)
class FQLLoss(ChunkCriticLoss):
    """FQL: chunk-critic TD, the one-step actor's distill-and-climb loss, and the flow's BC loss.

    Args:
        actor_network: mu, a :class:`~l1flow_rl.OneStepActor`.
        flow_network: the L1 Flow actor (the BC flow and distillation teacher).
        critic: a :class:`~l1flow_rl.networks.critic.ChunkCritic` on executed chunks [h, A].

    Keyword Args:
        alpha: weight of the distillation term (with ``normalize_q_loss``, FQL's README advises
            0.03-10; TorchRL 0.15's FQLLoss defaults to 10).
        normalize_q_loss: scale the Q term by 1 / mean|Q| (detached).
        td_options: ``gamma``, ``q_agg`` and ``rl_horizon`` of :class:`~l1flow_rl.ChunkCriticLoss`.

    Returns ``"loss_qvalue"``, ``"loss_actor"``, ``"loss_bc"`` and detached ``"q_actor_mean"``,
    ``"distill_loss"``, ``"lambda"`` and the critic diagnostics.
    """

    actor_network: OneStepActor
    actor_network_params: TensorDictBase
    target_actor_network_params: TensorDictBase

    def __init__(
        self,
        actor_network: OneStepActor,
        flow_network: L1FlowActor,
        critic: ChunkCritic,
        *,
        alpha: float = 10.0,
        normalize_q_loss: bool = True,
        **td_options: Any,
    ) -> None:
        if alpha < 0:
            raise ValueError(f"alpha must be >= 0, got {alpha}")
        super().__init__(critic, flow_network, **td_options)
        if not isinstance(actor_network, OneStepActor):
            raise TypeError(f"actor_network must be a OneStepActor, got {type(actor_network).__name__}")
        mu, flow = actor_network.policy, flow_network.policy
        for attr in ("action_dim", "obs_horizon", "pred_horizon", "action_steps"):
            if getattr(mu, attr) != getattr(flow, attr):
                raise ValueError(
                    f"the one-step actor's {attr}={getattr(mu, attr)} differs from the flow's "
                    f"{getattr(flow, attr)}"
                )
        self.convert_to_functional(actor_network, "actor_network")
        self.bc_loss = L1FlowLoss(flow_network)
        self.__dict__["flow"] = flow_network  # the BC flow (the acting start; its parameters are bc_loss's)
        self.alpha, self.normalize_q_loss = float(alpha), bool(normalize_q_loss)

    @property
    def mu(self) -> OneStepPolicy:
        return self.actor_network.policy

    @property
    def actor(self) -> OneStepActor:
        """The acting module: mu."""
        return self.actor_network

    def _noise(self, n: int, like: Tensor) -> Tensor:
        return torch.randn(
            n, self.reader.pred_horizon, self.reader.action_dim, dtype=like.dtype, device=like.device
        )

    def _env_executed(self, x: Tensor) -> Tensor:
        return self.reader.action_normalizer.unnormalize(self.executed(x))

    def next_value(self, td: TensorDictBase, next_obs: TensorDictBase) -> Tensor:
        scale = self.reader.action_normalizer.scale
        with self.actor_network_params.to_module(self.actor_network):
            x = self.mu.clipped(next_obs, self._noise(next_obs.shape[0], scale))
        return self.aggregate_target(self.q(next_obs, self._env_executed(x), target=True))

    @torch.no_grad()  # the teacher gets no gradient from distillation
    def teacher_chunk(self, obs: TensorDictBase, z: Tensor) -> Tensor:
        """The flow's 2-NFE chunk from noise ``z`` (normalised, clipped to the action range): mu's target."""
        flow = self.reader
        cond = flow.encode(obs)
        return clip_actions(flow.sampler(lambda xt, t: flow.denoise(xt, t, cond), z))

    def actor_terms(self, obs: TensorDictBase, x: Tensor, teacher: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The actor loss's parts at mu's raw chunk ``x`` (normalised): the distillation term
        ``||x - teacher||^2`` (mean over the chunk, x unclipped), the critics' mean value of the
        clipped x's executed steps per window (no gradient to the critics), and lambda (detached)."""
        distill = (x - teacher).square().mean()
        q = self.q(obs, self._env_executed(clip_actions(x)), detach=True).mean(-1)
        lam = 1.0 / q.abs().mean().detach().clamp_min(1e-6) if self.normalize_q_loss else q.new_ones(())
        return distill, q, lam

    def actor_loss(self, td: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        obs = self.read_observation(td, self.tensor_keys.observation)
        z = self._noise(obs.shape[0], self.reader.action_normalizer.scale)
        with self.actor_network_params.to_module(self.actor_network):
            x = self.mu.chunk(obs, z)
        distill, q, lam = self.actor_terms(obs, x, self.teacher_chunk(obs, z))
        loss = self.alpha * distill - lam * q.mean()
        return loss, {
            "q_actor_mean": q.mean().detach(),
            "distill_loss": distill.detach(),
            "lambda": lam.detach(),
        }

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        loss_q, out = self.qvalue_loss(tensordict)
        loss_actor, actor_out = self.actor_loss(tensordict)
        bc = self.bc_loss(tensordict)[self.bc_loss.loss_name]
        return TensorDict(
            {"loss_qvalue": loss_q, "loss_actor": loss_actor, "loss_bc": bc, **out, **actor_out},
            batch_size=[],
        )
