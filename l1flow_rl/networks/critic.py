"""Chunk critics: Q(s, a_{t:t+h}) on the observation history and the h actions executed from it.

As in QC-FQL, the critic scores a whole executed action chunk (flattened) instead of one action,
so its TD target spans h environment steps. The observation goes through the same kind of encoder
(and the same normalisers) as the actor's, so state and image observations are handled alike.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictParams
from tensordict.utils import NestedKey
from torch import Tensor, nn

from l1flow_rl.networks.encoders import ObservationEncoder
from l1flow_rl.normalizer import Normalizer, NormalizerDict

__all__ = ["ChunkCritic", "build_critics", "chunk_critic_module", "stack_critics"]

#: A plain tensor observation is this single encoder entry (the policy's convention).
_STATE_KEY = "state"


def layer_norm_mlp(
    in_dim: int, hidden_dims: Sequence[int], out_dim: int, activation: type[nn.Module] = nn.GELU
) -> nn.Sequential:
    """Linear -> LayerNorm -> activation per hidden layer, then a plain linear head (FQL's critic MLP)."""
    layers: list[nn.Module] = []
    for h in hidden_dims:
        layers += [nn.Linear(in_dim, h), nn.LayerNorm(h), activation()]
        in_dim = h
    layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


class ChunkCritic(nn.Module):
    """Q(s, a) for an observation history [*B, To, ...] and an executed action chunk [*B, h, A].

    Observations are normalised and encoded per step (features [N, To, F], flattened); actions are
    normalised with the actor's action normaliser and flattened; both go through a LayerNorm MLP to
    one value [*B, 1]. Build it from a policy with :meth:`from_policy` so it shares the policy's
    encoder design and normalisation statistics (its own copy: the critic's encoder is trained by
    the critic loss only).

    The forward pass checks shapes only (no data-dependent checks), so it runs under ``torch.vmap``
    across an ensemble.

    Examples:
        >>> import torch
        >>> from l1flow_rl import L1FlowActor
        >>> from l1flow_rl.networks.critic import ChunkCritic
        >>> actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
        >>> critic = ChunkCritic.from_policy(actor.policy, action_horizon=8, hidden_dims=(32, 32))
        >>> critic(torch.randn(3, 2, 5), torch.rand(3, 8, 2)).shape
        torch.Size([3, 1])
    """

    def __init__(
        self,
        encoder: ObservationEncoder,
        *,
        obs_horizon: int,
        action_dim: int,
        action_horizon: int,
        hidden_dims: Sequence[int] = (512, 512, 512, 512),
        activation: type[nn.Module] = nn.GELU,
        normalize_obs: bool = True,
    ) -> None:
        super().__init__()
        if obs_horizon < 1 or action_horizon < 1 or action_dim < 1:
            raise ValueError(
                f"obs_horizon, action_horizon and action_dim must be >= 1, got {obs_horizon}, "
                f"{action_horizon}, {action_dim}"
            )
        self.encoder = encoder
        self.obs_horizon, self.action_dim, self.action_horizon = obs_horizon, action_dim, action_horizon
        norm_shapes = {k: s for k, s in encoder.obs_shapes.items() if len(s) == 1} if normalize_obs else {}
        self.obs_normalizer = NormalizerDict(norm_shapes)
        self.action_normalizer = Normalizer(action_dim)
        in_dim = obs_horizon * encoder.feature_dim + action_horizon * action_dim
        self.mlp = layer_norm_mlp(in_dim, tuple(hidden_dims), 1, activation)

    @classmethod
    def from_policy(
        cls,
        policy: nn.Module,
        *,
        action_horizon: int,
        hidden_dims: Sequence[int] = (512, 512, 512, 512),
        activation: type[nn.Module] = nn.GELU,
    ) -> ChunkCritic:
        """A critic with a copy of ``policy``'s encoder (re-initialised) and its normaliser statistics.

        ``policy`` is a :class:`~l1flow_rl.policy.ChunkPolicy` (or an actor holding one).
        """
        policy = getattr(policy, "policy", policy)
        encoder = copy.deepcopy(policy.encoder)
        for module in encoder.modules():  # a fresh encoder: the critic learns its own features
            if module is not encoder and hasattr(module, "reset_parameters"):
                module.reset_parameters()
        critic = cls(
            encoder,
            obs_horizon=policy.obs_horizon,
            action_dim=policy.action_dim,
            action_horizon=action_horizon,
            hidden_dims=hidden_dims,
            activation=activation,
            normalize_obs=len(policy.obs_normalizer) > 0,
        )
        critic.obs_normalizer.load_state_dict(policy.obs_normalizer.state_dict())
        critic.action_normalizer.load_state_dict(policy.action_normalizer.state_dict())
        return critic.to(next(policy.parameters()).device)

    def _entries(self, observation: Tensor | TensorDictBase) -> tuple[TensorDictBase, tuple[int, ...]]:
        if isinstance(observation, Tensor):
            if set(self.encoder.obs_shapes) != {_STATE_KEY}:
                expected = sorted(self.encoder.obs_shapes)
                raise TypeError(f"the observation is a tensor, but the encoder expects entries {expected}")
            entries = {_STATE_KEY: observation}
        else:
            missing = [k for k in self.encoder.obs_shapes if observation.get(k, default=None) is None]
            if missing:
                expected = sorted(self.encoder.obs_shapes)
                raise KeyError(f"observation entries {missing} are missing; the encoder expects {expected}")
            entries = {k: observation.get(k) for k in self.encoder.obs_shapes}
        batch: tuple[int, ...] | None = None
        for k, v in entries.items():
            shape = (self.obs_horizon, *self.encoder.obs_shapes[k])
            if v.dim() < len(shape) or tuple(v.shape[-len(shape) :]) != shape:
                dims = ", ".join(map(str, shape))
                raise ValueError(
                    f"observation entry {k!r} must have shape [*B, {dims}], got {tuple(v.shape)}"
                )
            batch = tuple(v.shape[: v.dim() - len(shape)])
        assert batch is not None
        n = math.prod(batch)
        dtype = self.action_normalizer.scale.dtype
        flat = {
            k: (v.to(dtype) if v.is_floating_point() else v).reshape(
                n, self.obs_horizon, *self.encoder.obs_shapes[k]
            )
            for k, v in entries.items()
        }
        return TensorDict(flat, batch_size=[n, self.obs_horizon]), batch

    def forward(self, observation: Tensor | TensorDictBase, action_chunk: Tensor) -> Tensor:
        obs, batch = self._entries(observation)
        h, a = self.action_horizon, self.action_dim
        if tuple(action_chunk.shape) != (*batch, h, a):
            raise ValueError(
                f"the critic's action chunk must have shape {[*batch, h, a]} (batch, action_horizon, "
                f"action_dim), got {tuple(action_chunk.shape)}"
            )
        feats = self.encoder(self.obs_normalizer.normalize(obs))
        actions = self.action_normalizer.normalize(action_chunk.to(feats.dtype).reshape(-1, h, a))
        x = torch.cat([feats.reshape(feats.shape[0], -1), actions.reshape(actions.shape[0], -1)], dim=-1)
        return self.mlp(x).reshape(*batch, 1)


def chunk_critic_module(
    critic: ChunkCritic,
    *,
    observation_key: NestedKey = "observation",
    action_key: NestedKey = "action_chunk",
    out_key: NestedKey = "state_action_value",
) -> TensorDictModule:
    """``critic`` as a TensorDictModule reading (observation, executed chunk) and writing Q [*B, 1].

    :class:`~l1flow_rl.objectives.FlowQLoss` feeds it the executed part of a chunk
    (``action_chunk[..., To-1 : To-1+h, :]``) under its second in_key.
    """
    return TensorDictModule(critic, in_keys=[observation_key, action_key], out_keys=[out_key])


def build_critics(
    policy: nn.Module, *, num: int, action_horizon: int, hidden_dims: Sequence[int]
) -> list[TensorDictModule]:
    """``num`` independently initialised critic modules for ``policy`` (:meth:`ChunkCritic.from_policy`)."""
    return [
        chunk_critic_module(
            ChunkCritic.from_policy(policy, action_horizon=action_horizon, hidden_dims=hidden_dims)
        )
        for _ in range(num)
    ]


def stack_critics(critics: Sequence[TensorDictModule]) -> TensorDictParams:
    """The critics' parameters and buffers stacked along a leading ensemble dim (one copy)."""
    return TensorDictParams(TensorDict.from_modules(*critics).clone())
