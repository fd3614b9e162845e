"""Chunk critics: an ensemble of Q(s, a) on the observation history and a chunk-shaped input.

The input beside the observation is whatever the algorithm values: the h executed actions (QC, FQL:
Q-chunking's critic on the flattened chunk) or the sampler's input noise (DSRL's Q(s, w)). The
observation is read by the policy (:meth:`~l1flow_rl.modules.policy.ChunkPolicy.as_obs_dict`) before it
reaches the critic, which takes the flat TensorDict [N, To] that reader returns.

The ensemble's members share one observation encoder (trained by the critic loss; for state
observations it has no parameters) and each have their own LayerNorm MLP head (FQL's critic:
Linear -> LayerNorm -> GELU per hidden layer). The heads run as one batched matmul per layer, which is
what ``torch.vmap`` over E separate MLPs computes, without E module calls.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor, nn

from l1flow_rl.modules.normalizer import Normalizer, NormalizerDict
from l1flow_rl.networks.encoders import ObservationEncoder

__all__ = ["ChunkCritic", "EnsembleMLP", "critic_module", "fresh_encoder"]


def fresh_encoder(encoder: ObservationEncoder) -> ObservationEncoder:
    """A copy of ``encoder`` with new weights: a critic or an RL actor learns its own features."""
    encoder = copy.deepcopy(encoder)
    for module in encoder.modules():
        if module is not encoder and hasattr(module, "reset_parameters"):
            module.reset_parameters()
    return encoder


class EnsembleMLP(nn.Module):
    """E independent LayerNorm MLPs [N, in] -> [N, E] (one output each), weights stacked [E, ...].

    Each member is initialised as ``nn.Linear`` would be (uniform in +-1/sqrt(fan_in)), independently.

    Example:
        >>> import torch
        >>> EnsembleMLP(6, (32, 32), num_members=3)(torch.randn(5, 6)).shape
        torch.Size([5, 3])
    """

    def __init__(
        self,
        in_dim: int,
        hidden_dims: Sequence[int],
        *,
        num_members: int,
        activation: type[nn.Module] = nn.GELU,
    ) -> None:
        super().__init__()
        if num_members < 1 or in_dim < 1:
            raise ValueError(f"num_members and in_dim must be >= 1, got {num_members}, {in_dim}")
        self.num_members = int(num_members)
        dims = [int(in_dim), *map(int, hidden_dims), 1]
        # modules holding plain Parameters: TensorDict.to_module (target critics) swaps tensors into
        # them, which a ParameterList would re-wrap as trainable Parameters
        self.layers = nn.ModuleList(_EnsembleLinear(num_members, i, o) for i, o in itertools.pairwise(dims))
        self.norms = nn.ModuleList(_EnsembleLayerNorm(num_members, width) for width in dims[1:-1])
        self.activation = activation()

    def forward(self, x: Tensor) -> Tensor:
        h = x.unsqueeze(0).expand(self.num_members, *x.shape)  # [E, N, in]
        for i, layer in enumerate(self.layers):
            h = layer(h)
            if i < len(self.norms):
                h = self.activation(self.norms[i](h))
        return h.squeeze(-1).transpose(0, 1)  # [N, E]


class _EnsembleLinear(nn.Module):
    def __init__(self, num_members: int, fan_in: int, fan_out: int) -> None:
        super().__init__()
        bound = 1.0 / math.sqrt(fan_in)  # nn.Linear's default, drawn per member
        self.weight = nn.Parameter(torch.empty(num_members, fan_in, fan_out).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(num_members, 1, fan_out).uniform_(-bound, bound))

    def forward(self, x: Tensor) -> Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


class _EnsembleLayerNorm(nn.Module):
    def __init__(self, num_members: int, width: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(num_members, 1, width))
        self.bias = nn.Parameter(torch.zeros(num_members, 1, width))
        self.width = width

    def forward(self, x: Tensor) -> Tensor:
        return nn.functional.layer_norm(x, (self.width,)) * self.weight + self.bias


class ChunkCritic(nn.Module):
    """Q [N, E] of E critics for a read observation [N, To] and a chunk-shaped input [N, *input_shape].

    Args:
        encoder: per-step observation features (a copy of the policy's, re-initialised).
        obs_horizon: To.
        input_shape: the valued input's shape, e.g. (h, A) executed actions or (H, A) noise.
        num_critics: E.
        hidden_dims: each head's hidden widths (FQL: 4 x 512).
        normalize_input: the input is an action chunk in environment units, normalised with
            ``action_normalizer`` (the policy's statistics); False for noise, which is read as is.

    Build it with :meth:`from_policy`.

    Examples:
        >>> import torch
        >>> from l1flow_rl import L1FlowActor
        >>> from l1flow_rl.networks.critic import ChunkCritic
        >>> actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
        >>> critic = ChunkCritic.from_policy(actor.policy, input_shape=(8, 2), hidden_dims=(32,))
        >>> obs = actor.policy.as_obs_dict(torch.randn(3, 2, 5))
        >>> critic(obs, torch.rand(3, 8, 2)).shape
        torch.Size([3, 2])
    """

    def __init__(
        self,
        encoder: ObservationEncoder,
        *,
        obs_horizon: int,
        input_shape: Sequence[int],
        num_critics: int = 2,
        hidden_dims: Sequence[int] = (512, 512, 512, 512),
        normalize_input: bool = True,
        normalize_obs: bool = True,
    ) -> None:
        super().__init__()
        self.encoder = encoder
        self.obs_horizon = int(obs_horizon)
        self.input_shape = tuple(int(d) for d in input_shape)
        norm_shapes = {k: s for k, s in encoder.obs_shapes.items() if len(s) == 1} if normalize_obs else {}
        self.obs_normalizer = NormalizerDict(norm_shapes)
        self.normalize_input = bool(normalize_input)
        # an action chunk is normalised per action dim (the last one), with the policy's statistics
        self.action_normalizer = Normalizer(self.input_shape[-1])
        in_dim = self.obs_horizon * encoder.feature_dim + math.prod(self.input_shape)
        self.heads = EnsembleMLP(in_dim, hidden_dims, num_members=num_critics)

    @property
    def num_critics(self) -> int:
        return self.heads.num_members

    @classmethod
    def from_policy(
        cls,
        policy: nn.Module,
        *,
        input_shape: Sequence[int],
        num_critics: int = 2,
        hidden_dims: Sequence[int] = (512, 512, 512, 512),
        normalize_input: bool = True,
    ) -> ChunkCritic:
        """A critic with a re-initialised copy of ``policy``'s encoder and its normaliser statistics
        (``policy``: a :class:`~l1flow_rl.modules.policy.ChunkPolicy` or an actor holding one)."""
        policy = getattr(policy, "policy", policy)
        critic = cls(
            fresh_encoder(policy.encoder),
            obs_horizon=policy.obs_horizon,
            input_shape=input_shape,
            num_critics=num_critics,
            hidden_dims=hidden_dims,
            normalize_input=normalize_input,
            normalize_obs=len(policy.obs_normalizer) > 0,
        )
        critic.obs_normalizer.load_state_dict(policy.obs_normalizer.state_dict())
        if normalize_input:
            critic.action_normalizer.load_state_dict(policy.action_normalizer.state_dict())
        return critic.to(next(policy.parameters()).device)

    def forward(self, observation: TensorDictBase, value_input: Tensor) -> Tensor:
        n = observation.shape[0]
        if tuple(value_input.shape) != (n, *self.input_shape):
            raise ValueError(
                f"the critic's input must have shape {[n, *self.input_shape]}, got {tuple(value_input.shape)}"
            )
        feats = self.encoder(self.obs_normalizer.normalize(observation)).reshape(n, -1)
        x = value_input.to(feats.dtype)
        if self.normalize_input:
            x = self.action_normalizer.normalize(x)
        return self.heads(torch.cat([feats, x.reshape(n, -1)], dim=-1))


def critic_module(
    critic: ChunkCritic,
    *,
    observation_key: NestedKey = "observation",
    input_key: NestedKey = "critic_input",
    out_key: NestedKey = "state_action_value",
) -> TensorDictModule:
    """``critic`` as a TensorDictModule: (read observation [N, To], input [N, ...]) -> Q [N, E]."""
    return TensorDictModule(critic, in_keys=[observation_key, input_key], out_keys=[out_key])
