"""Best-of-N action selection (Q-chunking's "QC"): draw N chunks from the L1 Flow policy and execute
the one the critic ensemble values most.

The policy stays the behaviour-cloned one, so every executed chunk is one the demonstrations make
likely (the selection is an implicit KL constraint), and the critic only has to rank the policy's own
samples. The 2-NFE sampler is what makes this cheap: N chunks cost 2 batched network evaluations.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictParams
from tensordict.utils import NestedKey
from torch import Tensor

from l1flow_rl.actor import L1FlowActor
from l1flow_rl.flow.samplers import ChunkSampler
from l1flow_rl.policy import ChunkPolicy

__all__ = ["BestOfNActor"]


class BestOfNActor(TensorDictModuleBase):
    """Reads the observation history and writes the best of ``num_samples`` chunks of ``actor``.

    Args:
        actor: the L1 Flow actor whose chunks are drawn (writes the executable window [*B, K, A]).
        critic: a critic TensorDictModule (:func:`~l1flow_rl.networks.critic.chunk_critic_module`):
            the architecture only, run with each member's parameters in turn.
        critic_params: the ensemble's parameters, stacked along a leading dim of size Q (e.g.
            ``FlowQLoss.qvalue_network_params``, shared, so the actor follows the critics as they
            train). The score is the ensemble's mean.
        num_samples: N, chunks drawn per observation.
        rl_horizon: h, the executed steps the critic reads (the first h of the window).
        critic_input: ``"action"`` (the critics read the chunk) or ``"residual"`` (the chunk minus the
            policy's own chunk from zero noise at that state), as the critics were trained
            (:class:`~l1flow_rl.FlowQLoss`'s ``critic_input``).

    Under ``ExplorationType.DETERMINISTIC`` every draw starts from zero noise, so the N draws coincide
    and the choice is the policy's own deterministic chunk.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from l1flow_rl import L1FlowActor
        >>> from l1flow_rl.networks.best_of_n import BestOfNActor
        >>> from l1flow_rl.networks.critic import build_critics, stack_critics
        >>> actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
        >>> critics = build_critics(actor, num=2, action_horizon=8, hidden_dims=(32,))
        >>> best = BestOfNActor(actor, critics[0], stack_critics(critics), num_samples=16, rl_horizon=8)
        >>> best(TensorDict({"observation": torch.randn(3, 2, 5)}, [3]))["action_chunk"].shape
        torch.Size([3, 8, 2])
    """

    def __init__(
        self,
        actor: L1FlowActor,
        critic: TensorDictModule,
        critic_params: TensorDictBase,
        *,
        num_samples: int,
        rl_horizon: int,
        critic_input: str = "action",
    ) -> None:
        super().__init__()
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        if not 1 <= rl_horizon <= actor.policy.action_steps:
            raise ValueError(
                f"rl_horizon={rl_horizon} must lie in [1, action_steps={actor.policy.action_steps}]: the "
                "critic reads the first h steps of the executable window"
            )
        if critic_input not in ("action", "residual"):
            raise ValueError(f"critic_input must be 'action' or 'residual', got {critic_input!r}")
        if critic_params.batch_dims != 1:
            raise ValueError(
                f"critic_params must be stacked along one leading ensemble dim, got batch size "
                f"{list(critic_params.batch_size)}"
            )
        self.actor = actor
        self.critic_params = (
            critic_params if isinstance(critic_params, TensorDictParams) else TensorDictParams(critic_params)
        )
        # the architecture, not registered: its own tensors are never used (each member's are swapped
        # in), and the state_dict holds the ensemble once, in critic_params
        object.__setattr__(self, "_critic", critic)
        self.num_samples, self.rl_horizon = int(num_samples), int(rl_horizon)
        self.critic_input = critic_input
        self.in_keys: list[NestedKey] = list(actor.in_keys)
        self.out_keys: list[NestedKey] = list(actor.out_keys)

    @property
    def policy(self) -> ChunkPolicy:
        return self.actor.policy

    @property
    def sampler(self) -> ChunkSampler:
        return self.actor.sampler

    def with_sampler(self, sampler: str | ChunkSampler, **sampler_kwargs: Any) -> BestOfNActor:
        """The same selection over another sampler's chunks (see :meth:`L1FlowActor.with_sampler`)."""
        return BestOfNActor(
            self.actor.with_sampler(sampler, **sampler_kwargs),
            self._critic,
            self.critic_params,
            num_samples=self.num_samples,
            rl_horizon=self.rl_horizon,
            critic_input=self.critic_input,
        )

    @torch.no_grad()
    def reference_chunk(self, observation: Tensor | TensorDictBase) -> Tensor:
        """The policy's first h executed steps [N, h, A] from zero noise: what residual critics subtract."""
        return self.policy(observation, deterministic=True)[:, : self.rl_horizon]

    def q_values(
        self, observation: Tensor | TensorDictBase, chunk: Tensor, reference: Tensor | None = None
    ) -> Tensor:
        """The ensemble's mean Q [N] of executed chunks [N, h, A] (environment units); ``reference``:
        the residual critics' :meth:`reference_chunk` of ``observation``, when already computed."""
        if self.critic_input == "residual":
            chunk = chunk - (self.reference_chunk(observation) if reference is None else reference)
        obs = self.policy.as_obs_dict(observation)
        td = TensorDict({}, batch_size=[chunk.shape[0]])
        td.set(self._critic.in_keys[0], obs)
        td.set(self._critic.in_keys[1], chunk)
        values = []
        for i in range(self.critic_params.shape[0]):
            with self.critic_params[i].to_module(self._critic):
                values.append(self._critic(td.copy()).get(self._critic.out_keys[0]).reshape(-1))
        return torch.stack(values).mean(0)

    @torch.no_grad()
    def select(self, observation: Tensor | TensorDictBase) -> tuple[Tensor, Tensor, Tensor]:
        """For B observations [B, To, ...]: the chosen chunks [B, K, A], all draws [B, N, K, A] and
        their scores [B, N]."""
        b, n = observation.shape[0], self.num_samples
        repeated = observation.repeat_interleave(n, 0)  # row i*n + j: observation i, draw j
        chunks = self.policy(repeated)  # [b*n, K, A]
        reference = None
        if self.critic_input == "residual":  # once per observation, not once per draw
            reference = self.reference_chunk(observation).repeat_interleave(n, 0)
        scores = self.q_values(repeated, chunks[:, : self.rl_horizon], reference).reshape(b, n)
        draws = chunks.reshape(b, n, *chunks.shape[1:])
        return draws[torch.arange(b), scores.argmax(1)], draws, scores

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation = tensordict.get(self.in_keys[0], None)
        if observation is None:
            raise KeyError(f"{type(self).__name__} reads {self.in_keys[0]!r}, which the input lacks")
        batch = tuple(self.policy.batch_dims(observation))
        chosen, _, _ = self.select(observation.reshape(-1, *observation.shape[len(batch) :]))
        tensordict.set(self.out_keys[0], chosen.reshape(*batch, *chosen.shape[1:]))
        return tensordict
