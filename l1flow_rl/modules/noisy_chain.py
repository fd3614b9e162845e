"""L1 Flow's 2-NFE sampler with learned Gaussian noise after each step: a chain with an exact likelihood.

ReinFlow (Zhang et al., NeurIPS 2025; github ReinFlow/ReinFlow) fine-tunes few-step flow policies with
PPO by adding state- and time-dependent Gaussian noise after every step of the sampler. The discrete
chain is then a product of Gaussians, whose log-likelihood is exact: a policy gradient needs no ODE
likelihood, and the policy no longer depends on how much the input noise moves its actions
(``bench_noise_authority``). For L1 Flow's sampler (one Euler step to ``t1``, then the sample
prediction), with ``f`` the network and ``v = (f - x) / (1 - t)``:

    x_t1  ~ N((1 - t1) * x0 + t1 * f(x0, 0),  sigma(s, 0)^2)
    chunk ~ N(f(x_t1, t1),                     sigma(s, t1)^2)

``sigma`` is a small MLP on the observation's condition and the step's time features, squashed into
``[min_std, max_std]`` (ReinFlow bounds it: 0.08-0.14 on its robomimic tasks). As ``max_std`` goes to
0 the chain is the deterministic 2-NFE sampler from the same ``x0``. Everything is in the policy's
normalised action units; the environment gets ``policy.action_normalizer.unnormalize(chunk)``.

Hand-written: neither TorchRL nor tensordict has a distribution over a flow sampler's chain.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn

from l1flow_rl.flow.samplers import TwoStepSampler
from l1flow_rl.modules.policy import ChunkPolicy
from l1flow_rl.networks.unet1d import SinusoidalEmbedding

__all__ = ["NoiseStd", "NoisyTwoStepChain"]

_LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


class NoiseStd(nn.Module):
    """The chain's noise scale: ``[cond, time features] -> std [N, H * A]`` in ``[min_std, max_std]``.

    Args:
        cond_dim: size of the policy's global condition (``policy.encode``'s output).
        chunk_numel: ``H * A``.
        hidden_dims: the MLP's hidden widths.
        min_std, max_std: the bounds (``0 < min_std <= max_std``).
        time_dim: size of the sinusoidal time features.
    """

    def __init__(
        self,
        cond_dim: int,
        chunk_numel: int,
        *,
        hidden_dims: Sequence[int] = (256, 256),
        min_std: float = 0.08,
        max_std: float = 0.14,
        time_dim: int = 16,
    ) -> None:
        super().__init__()
        if not 0 < min_std <= max_std:
            raise ValueError(
                f"noise std bounds must satisfy 0 < min_std <= max_std, got {min_std}, {max_std}"
            )
        self.min_std, self.max_std = float(min_std), float(max_std)
        self.time = SinusoidalEmbedding(time_dim)
        layers: list[nn.Module] = []
        width = cond_dim + time_dim
        for h in hidden_dims:
            layers += [nn.Linear(width, h), nn.Mish()]
            width = h
        self.mlp = nn.Sequential(*layers, nn.Linear(width, chunk_numel))
        nn.init.zeros_(self.mlp[-1].weight)  # every unit starts at the middle of its range
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, cond: Tensor, t: Tensor) -> Tensor:
        h = self.mlp(torch.cat([cond, self.time(t).to(cond.dtype)], dim=-1))
        return self.min_std + (self.max_std - self.min_std) * torch.sigmoid(h)


class NoisyTwoStepChain(nn.Module):
    """A :class:`~l1flow_rl.modules.policy.ChunkPolicy` sampled by its 2-NFE chain with learned noise.

    Args:
        policy: an L1 Flow policy (its sampler a :class:`~l1flow_rl.flow.samplers.TwoStepSampler`); the
            chain trains its network.
        noise: the noise scale; built from the policy's sizes when None.

    Keyword Args:
        min_std, max_std, hidden_dims: :class:`NoiseStd`'s, when ``noise`` is None.

    :meth:`sample` returns the chain (``x0``, ``x_mid``, ``chunk``, normalised, [N, H, A]) and its
    ``log_prob`` [N]; :meth:`log_prob` scores a stored chain under the current weights (PPO's ratio).

    Example:
        >>> from l1flow_rl import L1FlowActor
        >>> policy = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32)).policy
        >>> chain = NoisyTwoStepChain(policy)
        >>> obs = torch.randn(3, 2, 5)  # [N, To, obs_dim]
        >>> out = chain.sample(obs)
        >>> out["chunk"].shape, out["log_prob"].shape
        (torch.Size([3, 16, 2]), torch.Size([3]))
        >>> bool(torch.allclose(chain.log_prob(obs, out["x0"], out["x_mid"], out["chunk"]), out["log_prob"]))
        True
    """

    def __init__(
        self,
        policy: ChunkPolicy,
        noise: NoiseStd | None = None,
        *,
        min_std: float = 0.08,
        max_std: float = 0.14,
        hidden_dims: Sequence[int] = (256, 256),
    ) -> None:
        super().__init__()
        if not isinstance(policy.sampler, TwoStepSampler):
            raise TypeError(
                f"NoisyTwoStepChain needs an L1 Flow policy (TwoStepSampler), got sampler {policy.sampler!r}"
            )
        self.policy = policy
        numel = policy.pred_horizon * policy.action_dim
        cond_dim = policy.net.global_cond_dim
        self.noise = noise or NoiseStd(
            cond_dim, numel, hidden_dims=hidden_dims, min_std=min_std, max_std=max_std
        )
        self.t1 = policy.sampler.t_first

    def _read(self, observation: TensorDictBase | Tensor) -> TensorDictBase:
        return self.policy.as_obs_dict(observation)

    def _std(self, cond: Tensor, t: float, like: Tensor) -> Tensor:
        return self.noise(
            cond, torch.full((like.shape[0],), t, dtype=like.dtype, device=like.device)
        ).view_as(like)

    def _moments(self, cond: Tensor, x: Tensor, t: float) -> tuple[Tensor, Tensor]:
        """Mean and std of the step that leaves time ``t`` from ``x``."""
        f = self.policy.denoise(x, torch.full((x.shape[0],), t, dtype=x.dtype, device=x.device), cond)
        mean = (1 - self.t1) * x + self.t1 * f if t == 0.0 else f  # the Euler step to t1; then f itself
        return mean, self._std(cond, t, x)

    @staticmethod
    def _gaussian_log_prob(x: Tensor, mean: Tensor, std: Tensor) -> Tensor:
        z = (x - mean) / std
        return (-0.5 * z.square() - std.log() - _LOG_SQRT_2PI).flatten(1).sum(-1)

    def sample(self, observation: TensorDictBase | Tensor, x0: Tensor | None = None) -> TensorDict:
        """A chain per observation: ``x0`` (given or drawn), ``x_mid`` (at ``t1``), ``chunk`` and the
        chain's ``log_prob`` given ``x0`` (``x0``'s own density carries no parameter)."""
        cond = self.policy.encode(self._read(observation))
        shape = (cond.shape[0], self.policy.pred_horizon, self.policy.action_dim)
        if x0 is None:
            x0 = torch.randn(shape, dtype=cond.dtype, device=cond.device)
        elif tuple(x0.shape) != shape:
            raise ValueError(
                f"x0 must have shape [N, pred_horizon, action_dim] = {list(shape)}, got {list(x0.shape)}"
            )
        mean1, std1 = self._moments(cond, x0, 0.0)
        x_mid = mean1 + std1 * torch.randn_like(mean1)
        mean2, std2 = self._moments(cond, x_mid, self.t1)
        chunk = mean2 + std2 * torch.randn_like(mean2)
        log_prob = self._gaussian_log_prob(x_mid, mean1, std1) + self._gaussian_log_prob(chunk, mean2, std2)
        return TensorDict(
            {"x0": x0, "x_mid": x_mid, "chunk": chunk, "log_prob": log_prob}, batch_size=[cond.shape[0]]
        )

    def log_prob(
        self, observation: TensorDictBase | Tensor, x0: Tensor, x_mid: Tensor, chunk: Tensor
    ) -> Tensor:
        """log p(x_mid, chunk | x0, s) [N] under the current weights (differentiable in both networks)."""
        cond = self.policy.encode(self._read(observation))
        mean1, std1 = self._moments(cond, x0, 0.0)
        mean2, std2 = self._moments(cond, x_mid, self.t1)
        return self._gaussian_log_prob(x_mid, mean1, std1) + self._gaussian_log_prob(chunk, mean2, std2)

    def entropy(self, observation: TensorDictBase | Tensor, x0: Tensor, x_mid: Tensor) -> Tensor:
        """The two steps' Gaussian entropies given the stored chain [N] (PPO's entropy bonus)."""
        cond = self.policy.encode(self._read(observation))
        per_unit = 0.5 + _LOG_SQRT_2PI
        return sum(
            (self._std(cond, t, x).log() + per_unit).flatten(1).sum(-1)
            for t, x in ((0.0, x0), (self.t1, x_mid))
        )
