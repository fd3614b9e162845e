"""Diffusion steering (DSRL-SAC, Wagenmaker et al. 2025) on the L1 Flow policy: SAC over (s, w).

The flow is frozen; a squashed-Gaussian policy (:class:`~l1flow_rl.NoiseActor`) picks its input noise
w within a bound, and the chunk executed is the flow's 2-NFE decoding of w. The critics value
Q(s, w) of the noise that was acted on (``"noise"`` in the batch), so an update evaluates no flow:

    y = R_h + g * (1 - terminated) * (Qbar(s_{t+h}, w') - a * log pi(w' | s_{t+h})),  w' ~ pi
    actor:  a * log pi(w | s) - Q(s, w),   w ~ pi (reparameterised)
    temperature: -log a * (log pi(w | s) + target_entropy)   (detached log pi)

with g = gamma per chunk decision and R_h the chunk's rewards summed, as DSRL's chunk-wrapped env
(``finetune.dsrl.discount_per_chunk``), or g = gamma^h and R_h discounted per env step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn

from l1flow_rl.finetune.base import ChunkCriticLoss
from l1flow_rl.finetune.dsrl.actor import NoiseActor, NoisePolicy
from l1flow_rl.networks.critic import ChunkCritic
from l1flow_rl.utils.doc_examples import FLOW, TRAIN_STEP, TRANSITIONS, add_example

__all__ = ["DSRLLoss", "sac_actor_terms"]


def sac_actor_terms(
    log_alpha: Tensor, log_prob: Tensor, q: Tensor, target_entropy: float
) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
    """SAC's actor and temperature losses from log pi(w | s) [N] of reparameterised draws and their value
    [N] under critics whose parameters are detached, with the detached diagnostics."""
    alpha = log_alpha.exp()
    loss_actor = (alpha.detach() * log_prob - q).mean()
    loss_alpha = -(log_alpha * (log_prob.detach() + target_entropy)).mean()
    out = {"alpha": alpha.detach(), "entropy": -log_prob.mean().detach(), "q_actor_mean": q.mean().detach()}
    return loss_actor, loss_alpha, out


@add_example(
    FLOW,
    """\
>>> from l1flow_rl import DSRLLoss, NoiseActor
>>> steer = NoiseActor.from_flow(flow, bound=1.5, hidden_dims=(64,))
>>> critic = ChunkCritic.from_policy(
...     flow, input_shape=(16, 2), hidden_dims=(32,), normalize_input=False
... )
>>> loss_fn = DSRLLoss(steer, critic)
""",
    TRANSITIONS,
    """\
>>> td["noise"] = torch.rand(4, 16, 2)  # the w each chunk was decoded from
""",
    TRAIN_STEP,
)
class DSRLLoss(ChunkCriticLoss):
    """SAC in the flow's noise space (DSRL's plain variant: the critic is Q(s, w)).

    Args:
        actor_network: a :class:`~l1flow_rl.NoiseActor`; only its noise policy is trained.
        critic: a :class:`~l1flow_rl.networks.critic.ChunkCritic` on noise [H, A]
            (``normalize_input=False``).

    Keyword Args:
        target_entropy: SAC's entropy target for log pi over the H x A noise (DSRL: 0).
        init_alpha: the starting temperature (1e-3: at SAC's 1 the entropy of the H x A noise swamps
            sparse rewards, see :class:`~l1flow_rl.finetune.dsrl.settings.DSRLSettings`).
        td_options: ``gamma``, ``q_agg`` and ``rl_horizon`` of :class:`~l1flow_rl.ChunkCriticLoss`
            (here ``q_agg`` defaults to ``min``, as SAC's).

    The batch holds ``"noise"`` [*B, H, A], the w its chunk was decoded from, besides the critic
    entries. Returns ``"loss_qvalue"``, ``"loss_actor"``, ``"loss_alpha"`` and detached
    ``"alpha"``, ``"entropy"``, ``"q_actor_mean"`` and the critic diagnostics.
    """

    @dataclass
    class _AcceptedKeys(ChunkCriticLoss._AcceptedKeys):
        """Configurable tensordict keys: those of :class:`~l1flow_rl.ChunkCriticLoss`, and

        Attributes:
            noise (NestedKey): the flow's input noise w [*B, H, A] the executed chunk came from.
                Defaults to ``"noise"``.
            step_counter (NestedKey): optional [*B, 1], ``MultiStepActorWrapper``'s count of the
                chunk's steps (1 at its first). Where present, only windows that start a chunk are
                valid: w describes the actions from there on. Defaults to ``"counter"``.
        """

        noise: NestedKey = "noise"
        step_counter: NestedKey = "counter"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    actor_network: NoisePolicy
    actor_network_params: TensorDictBase
    target_actor_network_params: TensorDictBase

    def __init__(
        self,
        actor_network: NoiseActor,
        critic: ChunkCritic,
        *,
        target_entropy: float = 0.0,
        init_alpha: float = 1e-3,
        **td_options: Any,
    ) -> None:
        if not isinstance(actor_network, NoiseActor):
            raise TypeError(f"actor_network must be a NoiseActor, got {type(actor_network).__name__}")
        super().__init__(critic, actor_network.flow, **{"q_agg": "min", **td_options})
        shape = actor_network.noise_policy.noise_shape
        if self.critic.input_shape != shape or self.critic.normalize_input:
            raise ValueError(
                f"DSRL's critic values the noise as is: build it with input_shape={list(shape)} and "
                f"normalize_input=False (got {list(self.critic.input_shape)}, {self.critic.normalize_input})"
            )
        if init_alpha <= 0:
            raise ValueError(f"init_alpha must be > 0, got {init_alpha}")
        self.convert_to_functional(actor_network.noise_policy, "actor_network")
        self.log_alpha = nn.Parameter(torch.tensor(math.log(init_alpha)))
        self.target_entropy = float(target_entropy)
        # the acting module (the frozen flow decodes its noise); not registered: its trained part
        # is this loss's actor_network
        self.__dict__["actor"] = actor_network

    @property
    def noise_policy(self) -> NoisePolicy:
        return self.actor_network

    def critic_input(self, td: TensorDictBase) -> Tensor:
        noise = self._get(
            td,
            self.tensor_keys.noise,
            f"the flow's input noise [*B, {', '.join(map(str, self.critic.input_shape))}]",
        )
        return noise.reshape(-1, *self.critic.input_shape)

    def valid(self, td: TensorDictBase, n: int) -> Tensor:
        valid = super().valid(td, n)
        counter = td.get(self.tensor_keys.step_counter, default=None)
        if counter is None:
            return valid
        return valid & (counter.reshape(n) == 1).to(valid.device)

    def _sample(self, obs: TensorDictBase) -> tuple[Tensor, Tensor]:
        with self.actor_network_params.to_module(self.actor_network):
            return self.noise_policy.sample(obs)

    def next_value(self, td: TensorDictBase, next_obs: TensorDictBase) -> Tensor:
        w, log_prob = self._sample(next_obs)
        value = self.aggregate_target(self.q(next_obs, w, target=True))
        return value - self.log_alpha.exp().detach() * log_prob

    def actor_loss(self, td: TensorDictBase) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """(actor loss, temperature loss, diagnostics)."""
        obs = self.read_observation(td, self.tensor_keys.observation)
        w, log_prob = self._sample(obs)
        q = self.q(obs, w, detach=True)
        # an ensemble with drawn target members (RLPD): the actor climbs the members' mean
        q = q.mean(-1) if self.target_critics is not None else self.aggregate(q)
        return sac_actor_terms(self.log_alpha, log_prob, q, self.target_entropy)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        loss_q, out = self.qvalue_loss(tensordict)
        loss_actor, loss_alpha, actor_out = self.actor_loss(tensordict)
        return TensorDict(
            {"loss_qvalue": loss_q, "loss_actor": loss_actor, "loss_alpha": loss_alpha, **out, **actor_out},
            batch_size=[],
        )
