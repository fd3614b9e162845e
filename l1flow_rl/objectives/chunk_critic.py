"""The chunk critic's TD loss, shared by QC, FQL and DSRL (each names its own next-chunk actor).

For a window at step t with h executed actions, the target is

    y = R_h + gamma^h * (1 - terminated) * Qbar(s_{t+h}, a'),     R_h = sum_{i<h} gamma^i r_{t+i}

with ``a'`` from the algorithm's next-chunk actor and ``Qbar`` the target critics aggregated by
``min`` or ``mean``. The windows (:func:`~l1flow_rl.data.rl_windows.read_rl_targets`) give
``("next", "terminated")`` only where an episode ended in a terminal state within the chunk; a
truncated episode bootstraps from its final observation. A chunk that crosses a terminal end is
valid: its return is summed to that end and nothing is bootstrapped. A chunk that crosses a
truncated end is not (``chunk_valid`` False) and drops out of the loss, as in QC.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.objectives import LossModule

from l1flow_rl.modules.policy import ChunkPolicy
from l1flow_rl.networks.critic import ChunkCritic, critic_module
from l1flow_rl.objectives.chunk_loss import required_entry
from l1flow_rl.utils.doc_examples import CRITIC, FLOW, TRAIN_STEP, TRANSITIONS, add_example

__all__ = ["ChunkCriticLoss"]

Q_AGGREGATIONS = ("mean", "min")


@add_example(
    FLOW,
    CRITIC,
    """\
>>> from l1flow_rl import ChunkCriticLoss
>>> bc_chunk = lambda obs: flow.policy(obs)  # the BC policy's next chunk: TD-only
>>> loss_fn = ChunkCriticLoss(critic, flow, next_actor=bc_chunk)
""",
    TRANSITIONS,
    TRAIN_STEP,
)
class ChunkCriticLoss(LossModule):
    """TD loss of an ensemble of chunk critics; usable alone with any next-chunk actor.

    Args:
        critic: a :class:`~l1flow_rl.networks.critic.ChunkCritic` (E members) or a
            TensorDictModule around one. Its target copy is made here (update it with TorchRL's
            ``SoftUpdate``).
        policy: the :class:`~l1flow_rl.modules.policy.ChunkPolicy` (or an actor holding one) whose reader
            validates observations and whose horizons locate the executed chunk; it is not trained here.

    Keyword Args:
        next_actor: ``read next observation [N, To] -> critic input [N, ...]``, the chunk valued at
            s_{t+h} (e.g. the BC policy's own chunk: a TD-only arm). Subclasses name their own
            actor in :meth:`next_value` instead.
        gamma: per-step discount; the bootstrap is discounted by ``gamma ** rl_horizon``. The
            windows' chunk returns must be discounted with the same gamma.
        q_agg: ``"mean"`` (QC, FQL) or ``"min"`` over the target critics.
        rl_horizon: h, executed actions per chunk (default: the policy's ``action_steps``).

    The input holds ``"observation"`` [*B, To, ...], ``"action_chunk"`` [*B, H, A] (its steps
    [To-1, To-1+h) are the executed ones), ``("next", "reward")`` [*B, 1] (the discounted chunk
    return), ``("next", "terminated")`` [*B, 1], ``("next", "observation")`` and ``"chunk_valid"``
    [*B, 1] (absent: all valid). Returns ``"loss_qvalue"`` and detached ``"q_data_mean"``,
    ``"target_mean"``, ``"td_error_abs"``, ``"valid_fraction"``.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            observation (NestedKey): observation history [*B, To, ...]. Defaults to ``"observation"``.
            action_chunk (NestedKey): the stored chunk [*B, H, A] in environment units.
                Defaults to ``"action_chunk"``.
            reward (NestedKey): read under ``"next"``: the discounted chunk return [*B, 1].
                Defaults to ``"reward"``.
            terminated (NestedKey): read under ``"next"``: no bootstrap where True.
                Defaults to ``"terminated"``.
            next_observation (NestedKey): the history h steps later. Defaults to ``("next", "observation")``.
            chunk_valid (NestedKey): [*B, 1] bool, False for windows left out of the critic loss.
                Defaults to ``"chunk_valid"``.
        """

        observation: NestedKey = "observation"
        action_chunk: NestedKey = "action_chunk"
        reward: NestedKey = "reward"
        terminated: NestedKey = "terminated"
        next_observation: NestedKey = ("next", "observation")
        chunk_valid: NestedKey = "chunk_valid"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    qvalue_network: TensorDictModule
    qvalue_network_params: TensorDictBase
    target_qvalue_network_params: TensorDictBase
    critic_diagnostics = ("q_data_mean", "target_mean", "td_error_abs", "valid_fraction")

    def __init__(
        self,
        critic: ChunkCritic | TensorDictModule,
        policy: torch.nn.Module,
        *,
        next_actor: Callable[[TensorDictBase], Tensor] | None = None,
        gamma: float = 0.99,
        q_agg: str = "mean",
        rl_horizon: int | None = None,
        target_critics: int | None = None,
    ) -> None:
        if q_agg not in Q_AGGREGATIONS:
            raise ValueError(f"q_agg must be one of {Q_AGGREGATIONS}, got {q_agg!r}")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must lie in [0, 1], got {gamma}")
        super().__init__()
        reader = getattr(policy, "policy", policy)
        if not isinstance(reader, ChunkPolicy):
            raise TypeError(
                f"policy must be a ChunkPolicy or an actor holding one, got {type(policy).__name__}"
            )
        # not a submodule: the policy is read (observations, horizons), never trained by this loss
        self.__dict__["reader"] = reader
        module = critic if isinstance(critic, TensorDictModule) else critic_module(critic)
        if not isinstance(module.module, ChunkCritic):
            raise TypeError(f"critic must be a ChunkCritic, got {type(module.module).__name__}")
        self.convert_to_functional(module, "qvalue_network", create_target_params=True)
        self.rl_horizon = int(rl_horizon or reader.action_steps)
        if not 1 <= self.rl_horizon <= reader.action_steps:
            raise ValueError(
                f"rl_horizon={self.rl_horizon} must lie in [1, action_steps={reader.action_steps}]"
            )
        self.gamma, self.q_agg = float(gamma), q_agg
        members = self.critic.num_critics
        if target_critics is not None and not 1 <= target_critics <= members:
            raise ValueError(f"target_critics={target_critics} must lie in [1, num_critics={members}]")
        self.target_critics = target_critics
        self._next_actor = next_actor

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass  # the target is computed here (one line, see td_target); no TorchRL value estimator

    @property
    def critic(self) -> ChunkCritic:
        return self.qvalue_network.module  # type: ignore[return-value]

    # -- reading the batch -------------------------------------------------------------------------
    def _get(self, td: TensorDictBase, key: NestedKey, what: str):
        return required_entry(td, key, what, type(self).__name__)

    def read_observation(self, td: TensorDictBase, key: NestedKey) -> TensorDictBase:
        """The observation under ``key`` through the policy's reader: a flat TensorDict [N, To]."""
        return self.reader.as_obs_dict(self._get(td, key, "an observation history"), key=str(key))

    def executed(self, chunk: Tensor) -> Tensor:
        """The executed steps [..., h, A] of stored or predicted chunks [..., H, A]."""
        start = self.reader.obs_horizon - 1
        return chunk[..., start : start + self.rl_horizon, :]

    def critic_input(self, td: TensorDictBase) -> Tensor:
        """What the critics value for the batch's windows: the executed actions (environment units)."""
        policy = self.reader
        chunk = self._get(td, self.tensor_keys.action_chunk, "the stored chunk [*B, H, A]")
        return self.executed(chunk.reshape(-1, policy.pred_horizon, policy.action_dim))

    def _column(self, td: TensorDictBase, key: NestedKey, n: int, what: str) -> Tensor:
        value = self._get(td, key, what)
        if value.numel() != n:
            raise ValueError(
                f"{key!r} ({what}) must hold one value per window ({n}), got {tuple(value.shape)}"
            )
        return value.reshape(n)

    def valid(self, td: TensorDictBase, n: int) -> Tensor:
        key = self.tensor_keys.chunk_valid
        if td.get(key, default=None) is None:
            return torch.ones(n, dtype=torch.bool)
        return self._column(td, key, n, "chunk validity").bool()

    # -- values ------------------------------------------------------------------------------------
    def q(
        self, observation: TensorDictBase, value_input: Tensor, *, target: bool = False, detach: bool = False
    ) -> Tensor:
        """Every critic's value [N, E]: online or ``target`` critics; ``detach``: no gradient reaches
        the critics' parameters (an actor's objective)."""
        if target:  # .data: a swap-in must not write the module's Parameter wrappers back into the targets
            params = self.target_qvalue_network_params.data
        else:
            params = self.qvalue_network_params.detach() if detach else self.qvalue_network_params
        with params.to_module(self.qvalue_network):
            return self.critic(observation, value_input)

    def aggregate(self, q: Tensor) -> Tensor:
        """[N, E] -> [N] by ``q_agg``."""
        return q.min(-1).values if self.q_agg == "min" else q.mean(-1)

    def aggregate_target(self, q: Tensor) -> Tensor:
        """The bootstrap's [N, E] -> [N]: ``q_agg`` over ``target_critics`` members drawn at random for
        the batch (RLPD/REDQ: min over 2 of 10), or over all of them."""
        if self.target_critics is not None:
            q = q[:, torch.randperm(q.shape[-1], device=q.device)[: self.target_critics]]
        return self.aggregate(q)

    def next_value(self, td: TensorDictBase, next_obs: TensorDictBase) -> Tensor:
        """Qbar(s_{t+h}, a') [N] with a' from the next-chunk actor (called under no_grad)."""
        if self._next_actor is None:
            raise NotImplementedError(
                f"{type(self).__name__} needs next_actor= (the chunk valued at the next observation)"
            )
        return self.aggregate_target(self.q(next_obs, self._next_actor(next_obs), target=True))

    @torch.no_grad()
    def td_target(self, td: TensorDictBase) -> Tensor:
        """y [N]: R_h + gamma^h * (1 - terminated) * next value."""
        keys = self.tensor_keys
        next_obs = self.read_observation(td, keys.next_observation)
        n = next_obs.shape[0]
        reward = self._column(td, ("next", keys.reward), n, "the discounted chunk return")
        terminated = self._column(td, ("next", keys.terminated), n, "terminal end within the chunk").bool()
        bootstrap = self.next_value(td, next_obs)
        return reward.to(bootstrap.dtype) + self.gamma**self.rl_horizon * (~terminated) * bootstrap

    def qvalue_loss(self, td: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        """Mean squared TD error of every critic over the valid windows, and its diagnostics."""
        obs = self.read_observation(td, self.tensor_keys.observation)
        n = obs.shape[0]
        target = self.td_target(td)
        valid = self.valid(td, n).to(target.device)
        q = self.q(obs, self.critic_input(td))  # [N, E]
        w = valid.to(q.dtype)
        count = w.sum().clamp_min(1)
        err = q - target.unsqueeze(-1)
        loss = (err.square().mean(-1) * w).sum() / count
        diagnostics = {
            "q_data_mean": (q.mean(-1) * w).sum() / count,
            "target_mean": (target * w).sum() / count,
            "td_error_abs": (err.abs().mean(-1) * w).sum() / count,
            "valid_fraction": w.mean(),
        }
        return loss, {k: v.detach() for k, v in diagnostics.items()}

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        loss, diagnostics = self.qvalue_loss(tensordict)
        return TensorDict({"loss_qvalue": loss, **diagnostics}, batch_size=[])
