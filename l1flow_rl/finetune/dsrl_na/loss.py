"""Diffusion steering with noise aliasing (DSRL-NA, Wagenmaker et al. 2025) on the L1 Flow policy.

Plain DSRL (:class:`~l1flow_rl.DSRLLoss`) values the noise w that was acted on, so it learns only from
its own steered episodes. DSRL-NA (the variant ajwagen/dsrl's robomimic configs run) learns an
action critic Q^A(s, a) on the executed chunks of any data, demonstrations included, and distils it
into a noise critic Q^W(s, w) through the frozen flow; the steering actor climbs Q^W. Many noises
decode to nearly the same chunk (the 2-NFE sampler barely depends on its noise), and Q^A sees them
as the one chunk they are:

    Q^A:   y = R_h + gamma^h * (1 - terminated) * (Qbar^A(s', decode(s', w')) - a * log pi(w' | s')),  w' ~ pi
    Q^W:   Q^W(s, w) -> agg Q^A(s, decode(s, w)),   w ~ N(0, I) clipped to the bound, and w ~ pi
    actor: a * log pi(w | s) - agg Q^W(s, w),   w ~ pi (reparameterised)

Public implementations fit Q^W on prior noises (a JAX one) or on the actor's (a PyTorch one); this one
fits both, half each (measured: see :meth:`DSRLNALoss.distill_loss`). One departure, for 2 CPU
cores: the prior noises are drawn once per observation and their decoded chunks kept
(:class:`~l1flow_rl.finetune.proposal_cache.ProposalCache`: the flow is frozen, so they never change); the
actor's noise, like the bootstrap's w', is decoded at every update.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import Tensor, nn

from l1flow_rl.finetune.base import ChunkCriticLoss
from l1flow_rl.finetune.dsrl.actor import NoiseActor, NoisePolicy
from l1flow_rl.finetune.dsrl.loss import sac_actor_terms
from l1flow_rl.finetune.proposal_cache import ProposalCache
from l1flow_rl.networks.critic import ChunkCritic, critic_module
from l1flow_rl.utils.doc_examples import CRITIC, FLOW, TRAIN_STEP, TRANSITIONS, add_example

__all__ = ["DSRLNALoss"]


@add_example(
    FLOW,
    CRITIC,
    """\
>>> from l1flow_rl import DSRLNALoss, NoiseActor
>>> steer = NoiseActor.from_flow(flow, bound=1.5, hidden_dims=(64,))
>>> noise_critic = ChunkCritic.from_policy(
...     flow, input_shape=(16, 2), hidden_dims=(32,), normalize_input=False
... )
>>> loss_fn = DSRLNALoss(steer, critic, noise_critic, distill_samples=2)
""",
    TRANSITIONS,
    TRAIN_STEP,
)
class DSRLNALoss(ChunkCriticLoss):
    """SAC in the flow's noise space on a noise critic distilled from a chunk-action critic (DSRL-NA).

    Args:
        actor_network: a :class:`~l1flow_rl.NoiseActor`; only its noise policy is trained.
        critic: the action critic Q^A, a :class:`~l1flow_rl.networks.critic.ChunkCritic` on executed
            chunks [h, A] (as QC's). Its target copy is made here (TorchRL's ``SoftUpdate``).
        noise_critic: Q^W, a ``ChunkCritic`` on the flow's noise [H, A] (``normalize_input=False``).

    Keyword Args:
        target_entropy: SAC's entropy target for log pi over the H x A noise (DSRL: 0).
        init_alpha: the starting temperature (see :class:`~l1flow_rl.DSRLLoss`).
        distill_samples: noises per observation that Q^W is fitted on, drawn and decoded once.
        cache_seed: mixed into those noises' seeds (the run's seed).
        td_options: ``gamma``, ``q_agg`` (default ``min``, as SAC's), ``rl_horizon`` and
            ``target_critics`` of :class:`~l1flow_rl.ChunkCriticLoss`.

    The batch holds the keys of :class:`~l1flow_rl.ChunkCriticLoss` only (no stored noise: any
    window of any data is valued by its executed actions). Returns ``"loss_qvalue"`` (Q^A's TD),
    ``"loss_noise_qvalue"`` (the distillation), ``"loss_actor"``, ``"loss_alpha"`` and detached
    ``"alpha"``, ``"entropy"``, ``"q_actor_mean"`` (Q^W at the actor's noise),
    ``"distill_target_mean"`` / ``"distill_target_actor_mean"`` (Q^A of the chunks decoded from the
    prior's / the actor's noise) and the critic diagnostics.
    """

    actor_network: NoisePolicy
    actor_network_params: TensorDictBase
    target_actor_network_params: TensorDictBase
    noise_qvalue_network: TensorDictModule
    noise_qvalue_network_params: TensorDictBase
    target_noise_qvalue_network_params: TensorDictBase

    def __init__(
        self,
        actor_network: NoiseActor,
        critic: ChunkCritic,
        noise_critic: ChunkCritic,
        *,
        target_entropy: float = 0.0,
        init_alpha: float = 1e-3,
        distill_samples: int = 4,
        cache_seed: int = 0,
        **td_options: Any,
    ) -> None:
        if not isinstance(actor_network, NoiseActor):
            raise TypeError(f"actor_network must be a NoiseActor, got {type(actor_network).__name__}")
        super().__init__(critic, actor_network.flow, **{"q_agg": "min", **td_options})
        if not critic.normalize_input:
            raise ValueError("the action critic values executed chunks: build it with normalize_input=True")
        shape = actor_network.noise_policy.noise_shape
        if noise_critic.input_shape != shape or noise_critic.normalize_input:
            raise ValueError(
                f"the noise critic values the noise as is: build it with input_shape={list(shape)} and "
                f"normalize_input=False (got {list(noise_critic.input_shape)}, "
                f"{noise_critic.normalize_input})"
            )
        if init_alpha <= 0:
            raise ValueError(f"init_alpha must be > 0, got {init_alpha}")
        if distill_samples < 1:
            raise ValueError(f"distill_samples must be >= 1, got {distill_samples}")
        self.convert_to_functional(actor_network.noise_policy, "actor_network")
        self.convert_to_functional(critic_module(noise_critic), "noise_qvalue_network")
        self.log_alpha = nn.Parameter(torch.tensor(math.log(init_alpha)))
        self.target_entropy = float(target_entropy)
        self.__dict__["actor"] = actor_network  # the acting module (the frozen flow decodes its noise)
        self.bound = actor_network.noise_policy.bound
        self.proposal_cache = ProposalCache(
            self._decode_executed,
            noise_shape=(int(distill_samples), *shape),
            seed=cache_seed,
        )

    @property
    def noise_critic(self) -> ChunkCritic:
        return self.noise_qvalue_network.module  # type: ignore[return-value]

    def _decode_executed(self, obs: TensorDictBase, noise: Tensor) -> Tensor:
        """The executed steps [N, ..., h, A] of the chunks decoded from noise [N, ..., H, A] at read
        observations [N, To], the noise clipped to the bound as the actor acts."""
        return self.executed(self.actor.decode(obs, noise.clamp(-self.bound, self.bound)))

    def q_noise(self, observation: TensorDictBase, noise: Tensor, *, detach: bool = False) -> Tensor:
        """Every noise critic's value [N, E] of noise [N, H, A]; ``detach``: for the actor's objective."""
        params = self.noise_qvalue_network_params
        with (params.detach() if detach else params).to_module(self.noise_qvalue_network):
            return self.noise_critic(observation, noise)

    def _sample(self, obs: TensorDictBase) -> tuple[Tensor, Tensor]:
        with self.actor_network_params.to_module(self.actor_network):
            return self.actor_network.sample(obs)

    def next_value(self, td: TensorDictBase, next_obs: TensorDictBase) -> Tensor:
        w, log_prob = self._sample(next_obs)
        chunk = self._decode_executed(next_obs, w)
        value = self.aggregate_target(self.q(next_obs, chunk, target=True))
        return value - self.log_alpha.exp().detach() * log_prob

    def distill_loss(self, td: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        """Q^W against Q^A of the decoded chunks, half on each observation's cached prior noises, half on
        a fresh draw of the actor's noise (decoded here): fitted on the prior alone, Q^W valued the
        actor's w far above what Q^A gave the chunks they decode to: the actor climbed the noise critic
        where it was never fitted."""
        obs = self.read_observation(td, self.tensor_keys.observation)
        prior, out = self._distill_prior(obs)
        with torch.no_grad():
            w, _ = self._sample(obs)
            target = self.aggregate(self.q(obs, self._decode_executed(obs, w)))
        on_actor = (self.q_noise(obs, w) - target.unsqueeze(-1)).square().mean()
        return 0.5 * (prior + on_actor), {**out, "distill_target_actor_mean": target.mean()}

    def _distill_prior(self, obs: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        """Q^W on each observation's cached prior noises against Q^A of their decoded chunks."""
        keys = self.proposal_cache.keys(obs)
        executed = self.proposal_cache(obs, keys=keys)  # [N, S, h, A]
        noise = torch.stack([self.proposal_cache.noise(k) for k in keys]).to(executed.device)
        noise = noise.clamp(-self.bound, self.bound)
        n, samples = executed.shape[:2]
        flat_obs = obs.unsqueeze(1).expand(n, samples, *obs.shape[1:]).reshape(n * samples, *obs.shape[1:])
        with torch.no_grad():
            target = self.aggregate(self.q(flat_obs, executed.flatten(0, 1)))
        q_w = self.q_noise(flat_obs, noise.flatten(0, 1))
        loss = (q_w - target.unsqueeze(-1)).square().mean()
        return loss, {"distill_target_mean": target.mean().detach()}

    def actor_loss(self, td: TensorDictBase) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
        """(actor loss, temperature loss, diagnostics) on the noise critic."""
        obs = self.read_observation(td, self.tensor_keys.observation)
        w, log_prob = self._sample(obs)
        q = self.aggregate(self.q_noise(obs, w, detach=True))
        return sac_actor_terms(self.log_alpha, log_prob, q, self.target_entropy)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        loss_q, out = self.qvalue_loss(tensordict)
        loss_distill, distill_out = self.distill_loss(tensordict)
        loss_actor, loss_alpha, actor_out = self.actor_loss(tensordict)
        cache = self.proposal_cache
        return TensorDict(
            {
                "loss_qvalue": loss_q,
                "loss_noise_qvalue": loss_distill,
                "loss_actor": loss_actor,
                "loss_alpha": loss_alpha,
                **out,
                **distill_out,
                **actor_out,
                "distill_cache_size": torch.tensor(float(len(cache))),
            },
            batch_size=[],
        )
