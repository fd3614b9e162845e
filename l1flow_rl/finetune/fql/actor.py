"""FQL's one-step policy mu(s, z): an MLP on [observation features, noise], no time input, trained from
scratch (:class:`~l1flow_rl.FQLLoss` distils the L1 Flow policy's 2-NFE chunk from the same noise
into it and pushes it up the critics).

mu's raw output is what is distilled; only the chunk that is executed or valued is clipped to the
action range (:meth:`OneStepPolicy.clipped`), as in seohongpark/fql: a unit pushed past a bound by the
Q term keeps the distillation's gradient pulling it back.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModule
from tensordict.nn.probabilistic import interaction_type
from torch import Tensor, nn

from l1flow_rl.modules.normalizer import Normalizer, NormalizerDict, clip_actions
from l1flow_rl.modules.policy import ChunkPolicy, ExecutesChunks
from l1flow_rl.networks.critic import fresh_encoder

__all__ = ["OneStepActor", "OneStepPolicy"]


class OneStepPolicy(nn.Module):
    """mu(s, z): read observation [N, To] and noise z [N, H, A] -> normalised chunk [N, H, A].

    :meth:`chunk` is the raw output (what distillation trains); :meth:`clipped` and the acting
    :meth:`forward` clip it to [-1, 1], the demonstrated action range under the ``limits`` normaliser
    (FQL clips the actions it executes and values, not the one it distils). Observations are read by
    the same reader as the flow's (:meth:`ChunkPolicy.as_obs_dict`: this class has the attributes it
    reads).
    """

    as_obs_dict = ChunkPolicy.as_obs_dict
    batch_dims = ChunkPolicy.batch_dims
    executable = ChunkPolicy.executable

    def __init__(self, flow: ChunkPolicy, hidden_dims: Sequence[int] = (512, 512, 512, 512)) -> None:
        super().__init__()
        self.encoder = fresh_encoder(flow.encoder)  # from scratch, like the MLP
        self.obs_normalizer: NormalizerDict = copy.deepcopy(flow.obs_normalizer)
        self.action_normalizer: Normalizer = copy.deepcopy(flow.action_normalizer)
        self.action_dim, self.obs_horizon = flow.action_dim, flow.obs_horizon
        self.pred_horizon, self.action_steps = flow.pred_horizon, flow.action_steps
        chunk = self.pred_horizon * self.action_dim
        layers: list[nn.Module] = []
        width = self.obs_horizon * self.encoder.feature_dim + chunk
        for h in hidden_dims:
            layers += [nn.Linear(width, h), nn.GELU()]
            width = h
        layers.append(nn.Linear(width, chunk))
        self.net = nn.Sequential(*layers)

    @property
    def dtype(self) -> torch.dtype:
        return next(self.net.parameters()).dtype

    def chunk(self, obs: TensorDictBase, noise: Tensor) -> Tensor:
        """The raw normalised chunk [N, H, A] (not clipped) for a read observation and noise."""
        feats = self.encoder(self.obs_normalizer.normalize(obs)).reshape(obs.shape[0], -1)
        out = self.net(torch.cat([feats, noise.reshape(noise.shape[0], -1)], -1))
        return out.reshape(noise.shape)

    def clipped(self, obs: TensorDictBase, noise: Tensor) -> Tensor:
        """The chunk that is executed and valued: :meth:`chunk` clipped to the action range."""
        return clip_actions(self.chunk(obs, noise))

    def forward(self, observation: Tensor | TensorDictBase, deterministic: bool | None = None) -> Tensor:
        """Executable window [*B, K, A] in environment units; noise is zero when deterministic."""
        if deterministic is None:
            deterministic = interaction_type() in (InteractionType.DETERMINISTIC, InteractionType.MODE)
        batch = self.batch_dims(observation)
        obs = self.as_obs_dict(observation)
        shape = (obs.shape[0], self.pred_horizon, self.action_dim)
        noise = (
            torch.zeros(shape, dtype=self.dtype) if deterministic else torch.randn(shape, dtype=self.dtype)
        )
        x = self.action_normalizer.unnormalize(
            self.clipped(obs, noise.to(self.action_normalizer.scale.device))
        )
        window = self.executable(x)
        return window.reshape(*batch, *window.shape[1:])


class OneStepActor(ExecutesChunks, TensorDictModule):
    """mu as a TensorDictModule: ``"observation"`` -> ``"action_chunk"`` [*B, K, A] (one network call).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from l1flow_rl import L1FlowActor, OneStepActor
        >>> flow = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
        >>> mu = OneStepActor.from_flow(flow, hidden_dims=(64, 64))
        >>> mu(TensorDict({"observation": torch.randn(3, 2, 5)}, [3]))["action_chunk"].shape
        torch.Size([3, 8, 2])
    """

    def __init__(
        self, policy: OneStepPolicy, *, in_keys=("observation",), out_keys=("action_chunk",)
    ) -> None:
        super().__init__(policy, in_keys=list(in_keys), out_keys=list(out_keys))

    @classmethod
    def from_flow(cls, flow: nn.Module, hidden_dims: Sequence[int] = (512, 512, 512, 512)) -> OneStepActor:
        """A fresh mu for ``flow`` (an L1 Flow actor or its ChunkPolicy): its horizons, encoder design
        and normaliser statistics, new weights."""
        policy = getattr(flow, "policy", flow)
        return cls(OneStepPolicy(policy, hidden_dims).to(next(policy.parameters()).device))

    @property
    def policy(self) -> OneStepPolicy:
        return self.module  # type: ignore[return-value]
