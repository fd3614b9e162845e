"""The chunked generative policy: normalise -> encode once -> sample a chunk -> unnormalise."""

from __future__ import annotations

import copy
from collections.abc import Mapping

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType
from tensordict.nn.probabilistic import interaction_type
from torch import Tensor, nn

from l1flow_rl.flow.samplers import ChunkSampler, check_sampler_fits
from l1flow_rl.modules.normalizer import Normalizer, NormalizerDict
from l1flow_rl.modules.observations import STATE_KEY, read_observations
from l1flow_rl.networks.encoders import ObservationEncoder

__all__ = ["STATE_KEY", "ChunkPolicy"]


class ExecutesChunks:
    """Mixin for the acting modules over a policy (``self.policy``): ``action_steps``, how many steps of
    each chunk they execute (``MultiStepActorWrapper``'s ``n_steps``)."""

    @property
    def action_steps(self) -> int:
        return self.policy.action_steps  # type: ignore[attr-defined]


class ChunkPolicy(nn.Module):
    """Everything needed to go from an observation history to an action chunk.

    The network works in normalised units; ``obs_normalizer`` and ``action_normalizer`` live in
    the state_dict so a saved policy acts in the environment's units.

    Args:
        net: the chunk denoiser (``ConditionalUnet1D`` or ``MLPDenoiser``, see
            :mod:`l1flow_rl.networks.registry`).
        encoder: observation entries [N, To, ...] -> features [N, To, F].
        sampler: integrates the network into a chunk; its ``prediction`` must match the loss.
        obs_horizon: To. pred_horizon: H. action_steps: K, the executable window.
    """

    def __init__(
        self,
        net: nn.Module,
        encoder: ObservationEncoder,
        sampler: ChunkSampler,
        *,
        action_dim: int,
        obs_horizon: int,
        pred_horizon: int,
        action_steps: int,
        normalize_obs: bool = True,
    ) -> None:
        super().__init__()
        if obs_horizon < 1 or pred_horizon < 1 or action_steps < 1:
            raise ValueError(
                f"horizons must be >= 1, got obs_horizon={obs_horizon}, pred_horizon={pred_horizon}, "
                f"action_steps={action_steps}"
            )
        if obs_horizon - 1 + action_steps > pred_horizon:
            raise ValueError(
                f"obs_horizon - 1 + action_steps = {obs_horizon - 1 + action_steps} exceeds pred_horizon="
                f"{pred_horizon}: the executable window [To-1, To-1+K) must fit in the predicted chunk"
            )
        if net.global_cond_dim != obs_horizon * encoder.feature_dim:
            raise ValueError(
                f"net.global_cond_dim={net.global_cond_dim} must equal obs_horizon * encoder.feature_dim "
                f"= {obs_horizon} * {encoder.feature_dim}"
            )
        built_for = getattr(net, "horizon", None)  # a network over the flattened chunk has one length
        if built_for is not None and built_for != pred_horizon:
            raise ValueError(
                f"pred_horizon={pred_horizon}, but the network was built for chunks of {built_for}"
            )
        if pred_horizon % net.horizon_multiple:
            raise ValueError(
                f"pred_horizon={pred_horizon} must be divisible by {net.horizon_multiple} "
                f"(2 ** (len(down_dims) - 1) for down_dims={net.down_dims})"
            )
        if net.action_dim != action_dim:
            raise ValueError(f"net.action_dim={net.action_dim} differs from action_dim={action_dim}")
        if sampler.uses_timestep != bool(net.timestep_embed_dim):
            raise ValueError(
                f"{sampler!r} {'needs' if sampler.uses_timestep else 'takes no'} timestep, but the network "
                f"was built with timestep_embed_dim={net.timestep_embed_dim}"
            )
        self.net, self.encoder, self.sampler = net, encoder, sampler
        self.action_dim, self.obs_horizon = action_dim, obs_horizon
        self.pred_horizon, self.action_steps = pred_horizon, action_steps
        norm_shapes = {k: s for k, s in encoder.obs_shapes.items() if len(s) == 1} if normalize_obs else {}
        self.obs_normalizer = NormalizerDict(norm_shapes)
        self.action_normalizer = Normalizer(action_dim)

    # -- sampler swap (re-scoring one trained network under another sampler) -----------------
    def _check_sampler(self, sampler: ChunkSampler) -> None:
        check_sampler_fits(self.sampler, sampler)  # the current sampler stands for what the net learnt
        if sampler.uses_timestep != bool(self.net.timestep_embed_dim):
            raise ValueError(
                f"{sampler!r} {'needs' if sampler.uses_timestep else 'takes no'} timestep, but the network "
                f"was built with timestep_embed_dim={self.net.timestep_embed_dim}"
            )

    def set_sampler(self, sampler: ChunkSampler) -> ChunkPolicy:
        """Sample with ``sampler`` from now on; refused (listing the samplers that fit) when it reads
        another prediction type than the network was trained for."""
        self._check_sampler(sampler)
        self.sampler = sampler
        return self

    def with_sampler(self, sampler: ChunkSampler) -> ChunkPolicy:
        """A policy that shares this one's network, encoder and normalisers (the same tensors) and
        samples with ``sampler``; this policy is unchanged."""
        self._check_sampler(sampler)
        clone = copy.copy(self)
        for registry in ("_parameters", "_buffers", "_modules"):  # own registries, shared members
            clone.__dict__[registry] = dict(self.__dict__[registry])
        clone.sampler = sampler
        return clone

    # -- observation handling -------------------------------------------------------------
    def as_obs_dict(self, observation: Tensor | TensorDictBase, key: str = "observation") -> TensorDictBase:
        """Validate an observation (tensor or TensorDict of entries) with batch dims [*B, To, ...]
        and return it as a TensorDict flattened to batch [N, To]. Flat entries are cast to the
        network's dtype; image entries ([3, H, W] per step) must be uint8 and stay uint8 here
        (:func:`~l1flow_rl.modules.observations.read_observations`)."""
        return read_observations(observation, self.encoder.obs_shapes, self.obs_horizon, self.dtype, key=key)[
            0
        ]

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the network; observations and actions are cast to it."""
        return next(self.net.parameters()).dtype

    def encode(self, obs: TensorDictBase) -> Tensor:
        """Normalised global condition [N, To * F] from a flattened observation TensorDict."""
        feats = self.encoder(self.obs_normalizer.normalize(obs))
        return feats.reshape(feats.shape[0], -1)

    def denoise(self, x: Tensor, t: Tensor | None, cond: Tensor) -> Tensor:
        return self.net(x, t, cond)

    # -- acting -----------------------------------------------------------------------------
    def sample_chunk(
        self,
        observation: Tensor | TensorDictBase,
        *,
        deterministic: bool = False,
        generator: torch.Generator | None = None,
        noise: Tensor | None = None,
        inner_noise: Tensor | None = None,
    ) -> Tensor:
        """Full predicted chunk [*B, H, A] in environment units. ``noise`` [*B, H, A], when given, is the
        starting point instead of a fresh draw (reproducible chunks; what an exported program takes).
        ``inner_noise`` [*B, draws, H, A]: the draws a re-noising sampler makes after its start
        (``sampler.inner_noise_draws``: DDPM's, a chained Consistency Policy's), given instead of drawn."""
        batch = self.batch_dims(observation)
        obs = self.as_obs_dict(observation)
        cond = self.encode(obs)  # once per chunk, shared by every network call
        n = cond.shape[0]
        shape = (n, self.pred_horizon, self.action_dim)
        if noise is not None:
            if tuple(noise.shape) != (*batch, self.pred_horizon, self.action_dim):
                raise ValueError(
                    f"noise must have shape [*B, pred_horizon, action_dim] = "
                    f"{[*batch, self.pred_horizon, self.action_dim]}, got {list(noise.shape)}"
                )
            x_init = noise.reshape(shape).to(device=cond.device, dtype=cond.dtype)
        elif deterministic:
            x_init = torch.zeros(shape, device=cond.device, dtype=cond.dtype)
        else:
            x_init = torch.randn(shape, device=cond.device, dtype=cond.dtype, generator=generator)
        extra = {}
        if inner_noise is not None:
            draws = self.sampler.inner_noise_draws
            want = (*batch, draws, self.pred_horizon, self.action_dim)
            if not draws or tuple(inner_noise.shape) != want:
                raise ValueError(
                    f"inner_noise must have shape [*B, draws, pred_horizon, action_dim] = {list(want)} "
                    f"({self.sampler!r} draws {draws} times after its start), got {list(inner_noise.shape)}"
                )
            extra["inner_noise"] = inner_noise.reshape(n, *want[-3:]).to(device=cond.device, dtype=cond.dtype)
        x1 = self.sampler(
            lambda x, t: self.denoise(x, t, cond),
            x_init,
            deterministic=deterministic,
            generator=generator,
            **extra,
        )
        return self.action_normalizer.unnormalize(x1).reshape(*batch, self.pred_horizon, self.action_dim)

    def executable(self, chunk: Tensor) -> Tensor:
        """Steps [To-1, To-1+K) of a predicted chunk: the ones aligned with the current observation onward."""
        start = self.obs_horizon - 1
        return chunk[..., start : start + self.action_steps, :]

    def forward(
        self,
        observation: Tensor | TensorDictBase,
        deterministic: bool | None = None,
        noise: Tensor | None = None,
        inner_noise: Tensor | None = None,
    ) -> Tensor:
        """Executable window [*B, K, A]. ``deterministic=None`` follows TensorDict's interaction type:
        DETERMINISTIC (and MODE) start from zero noise, anything else samples; ``noise`` [*B, H, A]
        given starts from it, and ``inner_noise`` (a re-noising sampler's later draws, see
        :meth:`sample_chunk`) replaces its own draws."""
        if deterministic is None:
            deterministic = interaction_type() in (InteractionType.DETERMINISTIC, InteractionType.MODE)
        chunk = self.sample_chunk(
            observation, deterministic=deterministic, noise=noise, inner_noise=inner_noise
        )
        return self.executable(chunk)

    def batch_dims(self, observation: Tensor | TensorDictBase) -> tuple[int, ...]:
        """The leading batch dims [*B] of an observation [*B, To, ...]."""
        if isinstance(observation, Tensor):
            first = observation
            shape: tuple[int, ...] = self.encoder.obs_shapes.get(STATE_KEY, ())
        else:
            k = next(iter(self.encoder.obs_shapes))
            if k not in observation:
                return ()  # as_obs_dict raises the informative error
            first, shape = observation.get(k), self.encoder.obs_shapes[k]
        return tuple(first.shape[: max(first.dim() - len(shape) - 1, 0)])

    # -- fitting normalisers from data -----------------------------------------------------
    def fit_normalizers(
        self,
        observation: Mapping[str, Tensor] | Tensor | None = None,
        action: Tensor | None = None,
        mode: str = "limits",
        obs_mode: str | None = None,
    ) -> ChunkPolicy:
        """Fit the normalisers from samples (entries [..., D] and actions [..., A])."""
        if observation is not None:
            data = {STATE_KEY: observation} if isinstance(observation, Tensor) else observation
            self.obs_normalizer.fit(data, obs_mode or mode)  # type: ignore[arg-type]
        if action is not None:
            self.action_normalizer.fit(action, mode, name="action")  # type: ignore[arg-type]
        return self
