"""DSRL's noise-space actor: a squashed Gaussian picks the 2-NFE sampler's input noise w within a bound,
and the frozen L1 Flow policy decodes it into the executed chunk.

The flow maps noise to a chunk deterministically in two network calls, so steering its input is a
cheap, bounded way to change behaviour without touching the behaviour-cloned weights: no gradient
passes through the flow, and :class:`~l1flow_rl.DSRLLoss` never evaluates it.

Steering the noise moves the executed actions only as far as the sampler lets the noise matter. The
2-NFE L1 Flow sampler, trained on unimodal demonstrations, is nearly deterministic in its noise
(``benchmarks/results/noise_authority.json``: on PickCube the executed positions move far less over
noise draws than over states). A bounded residual on the executed window instead (Policy
Decorator's) was tried and retired: its actor followed the critics' extrapolation (their bias on
its data: ``benchmarks/results/critic_bias_maniskill_pickcube_residual.json``) and validated below its
start (docs/finetune.md).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModuleBase
from tensordict.nn.probabilistic import interaction_type
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.modules import TanhNormal

from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.modules.normalizer import NormalizerDict
from l1flow_rl.modules.policy import ChunkPolicy, ExecutesChunks
from l1flow_rl.networks.critic import fresh_encoder

__all__ = ["NoiseActor", "NoisePolicy", "PriorNoise"]


class NoisePolicy(nn.Module):
    """pi(w | s): read observation [N, To] -> a TanhNormal over w in [-bound, bound]^(H x A).

    An MLP (LayerNorm, as DSRL's) on the observation features gives the mean and, through a
    softplus, the scale of a Gaussian that ``tanh`` squashes into the bound (TorchRL's ``TanhNormal``).
    """

    def __init__(
        self,
        flow: ChunkPolicy,
        *,
        bound: float = 1.5,
        hidden_dims: Sequence[int] = (512, 512, 512),
        noise_shape: Sequence[int] | None = None,
    ) -> None:
        super().__init__()
        if bound <= 0:
            raise ValueError(f"the noise bound must be > 0, got {bound}")
        self.bound = float(bound)
        self.encoder = fresh_encoder(flow.encoder)
        self.obs_normalizer: NormalizerDict = copy.deepcopy(flow.obs_normalizer)
        self.noise_shape = tuple(noise_shape or (flow.pred_horizon, flow.action_dim))
        dim = math.prod(self.noise_shape)
        layers: list[nn.Module] = []
        width = flow.obs_horizon * self.encoder.feature_dim
        for h in hidden_dims:
            layers += [nn.Linear(width, h), nn.LayerNorm(h), nn.GELU()]
            width = h
        layers.append(nn.Linear(width, 2 * dim))
        self.net = nn.Sequential(*layers)

    def distribution(self, obs: TensorDictBase) -> TanhNormal:
        """The policy at read observations [N, To]: a distribution over flat w [N, H * A]."""
        feats = self.encoder(self.obs_normalizer.normalize(obs)).reshape(obs.shape[0], -1)
        loc, scale = self.net(feats).chunk(2, -1)
        scale = nn.functional.softplus(scale).clamp(1e-4, 10.0)
        return TanhNormal(loc, scale, low=-self.bound, high=self.bound)

    def sample(self, obs: TensorDictBase, *, deterministic: bool = False) -> tuple[Tensor, Tensor]:
        """(w [N, H, A], log pi(w | s) [N]); deterministic: the squashed mean, log-prob NaN."""
        dist = self.distribution(obs)
        if deterministic:
            w = dist.deterministic_sample
            log_prob = torch.full(w.shape[:1], float("nan"), dtype=w.dtype, device=w.device)
        else:
            w = dist.rsample()
            log_prob = dist.log_prob(w)
        return w.reshape(obs.shape[0], *self.noise_shape), log_prob


class PriorNoise(nn.Module):
    """The BC policy's steering input, acting with :class:`NoisePolicy`'s interface (the warm-up steps;
    log-probabilities are not defined): the flow's own input distribution, w ~ N(0, I) clipped to the
    bound."""

    def __init__(self, noise_shape: Sequence[int], bound: float) -> None:
        super().__init__()
        self.noise_shape, self.bound = tuple(noise_shape), float(bound)

    def sample(self, obs: TensorDictBase, *, deterministic: bool = False) -> tuple[Tensor, Tensor]:
        shape = (obs.shape[0], *self.noise_shape)
        if deterministic:
            w = torch.zeros(shape)
        else:
            w = torch.randn(shape).clamp(-self.bound, self.bound)
        return w, torch.full(shape[:1], float("nan"))


class NoiseActor(ExecutesChunks, TensorDictModuleBase):
    """Writes the flow's window ``"action_chunk"`` [*B, K, A] decoded (one 2-NFE call) from the steering
    noise w [*B, H, A], and ``"noise_chunk"`` [*B, K, H, A]: w once per executed step, so that
    TorchRL's ``MultiStepActorWrapper`` hands every step of the chunk its ``"noise"`` (and the replay
    buffer stores, at each chunk's first step, the w that chunk came from). The flow is frozen here.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from l1flow_rl import L1FlowActor, NoiseActor
        >>> flow = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
        >>> steer = NoiseActor.from_flow(flow, bound=1.5, hidden_dims=(64,))
        >>> out = steer(TensorDict({"observation": torch.randn(3, 2, 5)}, [3]))
        >>> out["action_chunk"].shape, out["noise_chunk"].shape, bool(out["noise_chunk"].abs().max() <= 1.5)
        (torch.Size([3, 8, 2]), torch.Size([3, 8, 16, 2]), True)
    """

    def __init__(
        self,
        flow: L1FlowActor,
        noise_policy: NoisePolicy,
        *,
        in_keys: Sequence[NestedKey] = ("observation",),
        out_keys: Sequence[NestedKey] = ("action_chunk", "noise_chunk"),
    ) -> None:
        super().__init__()
        self.flow = flow.requires_grad_(False)
        self.noise_policy = noise_policy
        expected = self._steered_shape(flow.policy)
        if tuple(noise_policy.noise_shape) != expected:
            shape, want = list(noise_policy.noise_shape), list(expected)
            raise ValueError(f"the steering policy's shape {shape} must be the flow's noise [H, A] = {want}")
        self.in_keys: list[NestedKey] = list(in_keys)
        self.out_keys: list[NestedKey] = list(out_keys)

    @staticmethod
    def _steered_shape(policy: ChunkPolicy) -> tuple[int, int]:
        return policy.pred_horizon, policy.action_dim

    @classmethod
    def from_flow(
        cls,
        flow: L1FlowActor,
        *,
        bound: float = 1.5,
        hidden_dims: Sequence[int] = (512, 512, 512),
    ) -> NoiseActor:
        shape = cls._steered_shape(flow.policy)
        policy = NoisePolicy(flow.policy, bound=bound, hidden_dims=hidden_dims, noise_shape=shape)
        return cls(flow, policy.to(next(flow.policy.parameters()).device))

    def prior(self) -> NoiseActor:
        """The BC policy, writing the same keys: what the steering collects with before its first
        update: the flow acts on w ~ N(0, I) clipped to the bound (DSRL)."""
        bound = self.noise_policy.bound
        return NoiseActor(
            self.flow,
            PriorNoise(self.noise_policy.noise_shape, bound),
            in_keys=self.in_keys,
            out_keys=self.out_keys,
        )

    @property
    def policy(self) -> ChunkPolicy:
        return self.flow.policy

    @torch.no_grad()
    def decode(self, obs: TensorDictBase, noise: Tensor) -> Tensor:
        """The full chunks [N, ..., H, A] (environment units) decoded from the flow's input noise
        [N, ..., H, A] at read observations [N, To]: several noises per observation encode it once."""
        policy = self.policy
        cond = policy.encode(obs)
        per_obs = math.prod(noise.shape[1:-2])
        if per_obs != 1:
            cond = cond.repeat_interleave(per_obs, 0)
        start = noise.reshape(-1, *noise.shape[-2:]).to(device=cond.device, dtype=cond.dtype)
        x1 = policy.sampler(lambda x, t: policy.denoise(x, t, cond), start)
        return policy.action_normalizer.unnormalize(x1).reshape(noise.shape)

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        observation = tensordict.get(self.in_keys[0], None)
        if observation is None:
            raise KeyError(f"{type(self).__name__} reads {self.in_keys[0]!r}, which the input lacks")
        policy = self.policy
        batch = tuple(policy.batch_dims(observation))
        obs = policy.as_obs_dict(observation, key=str(self.in_keys[0]))
        deterministic = interaction_type() in (InteractionType.DETERMINISTIC, InteractionType.MODE)
        noise, _ = self.noise_policy.sample(obs, deterministic=deterministic)
        window = policy.executable(self.decode(obs, noise))
        tensordict.set(self.out_keys[0], window.reshape(*batch, *window.shape[1:]))
        per_step = noise.unsqueeze(1).expand(-1, window.shape[1], *noise.shape[1:])
        tensordict.set(self.out_keys[1], per_step.reshape(*batch, *per_step.shape[1:]))
        return tensordict
