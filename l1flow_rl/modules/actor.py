"""The chunk actor as a TensorDictModule: observation history in, executable action window out."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, dispatch
from tensordict.utils import NestedKey

from l1flow_rl.export import folder as pretrained_folder
from l1flow_rl.flow.samplers import ChunkSampler, TwoStepSampler, make_sampler
from l1flow_rl.modules.policy import STATE_KEY, ChunkPolicy
from l1flow_rl.networks.encoders import AUTO, ObservationEncoder, StateEncoder, make_encoder
from l1flow_rl.networks.registry import DEFAULT_NETWORK, make_network, network_config

__all__ = ["L1FlowActor"]


class L1FlowActor(TensorDictModule):
    """Reads ``in_keys[0]`` (observation history [*B, To, ...]) and writes ``out_keys[0]`` (the
    executable window [*B, K, A]: steps [To-1, To-1+K) of the predicted horizon H).

    The writing key defaults to ``"action_chunk"``, which TorchRL's ``MultiStepActorWrapper``
    maps to the env's ``"action"``. The sampler is pluggable; the default is L1 Flow's
    ``TwoStepSampler(0.5)`` (2 network evaluations per chunk). Under
    ``set_exploration_type(ExplorationType.DETERMINISTIC)`` the chunk starts from zero noise.

    The baselines use the same actor with their own sampler: ``DDPMSampler()`` / ``DDIMSampler(k)``
    for :class:`~l1flow_rl.DiffusionLoss`, ``VelocityEulerSampler(10)`` for
    :class:`~l1flow_rl.FlowMatchingLoss`, ``DirectSampler()`` for :class:`~l1flow_rl.RegressionLoss`.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from l1flow_rl import L1FlowActor
        >>> actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(32, 64))
        >>> actor(TensorDict({"observation": torch.randn(3, 2, 5)}, batch_size=[3]))["action_chunk"].shape
        torch.Size([3, 8, 2])
    """

    def __init__(
        self,
        policy: ChunkPolicy,
        *,
        in_keys: Sequence[NestedKey] = ("observation",),
        out_keys: Sequence[NestedKey] = ("action_chunk",),
    ) -> None:
        super().__init__(policy, in_keys=list(in_keys), out_keys=list(out_keys))

    @dispatch(auto_batch_size=False)
    def forward(
        self,
        tensordict: TensorDictBase,
        *args: Any,
        tensordict_out: TensorDictBase | None = None,
        **kwargs: Any,
    ) -> TensorDictBase:
        """One key in, one key out. Written out because TensorDictModule's generic path wraps each
        output with ``TensorDict.from_any``, whose import probe on every call is a noticeable share
        of a batch-1 chunk's time on a CPU."""
        if args:
            raise ValueError(
                f"{type(self).__name__} takes one TensorDict, got {len(args)} more positional arguments"
            )
        observation = tensordict.get(self.in_keys[0], None)
        if observation is None:
            raise KeyError(
                f"{type(self).__name__} reads {self.in_keys[0]!r}, which the input lacks; it has "
                f"{sorted(map(str, tensordict.keys(include_nested=True, leaves_only=True)))}"
            )
        out = tensordict if tensordict_out is None else tensordict_out
        out.set(self.out_keys[0], self.module(observation, **kwargs))
        return out

    @property
    def policy(self) -> ChunkPolicy:
        return self.module  # type: ignore[return-value]

    @property
    def sampler(self) -> ChunkSampler:
        return self.policy.sampler

    def with_sampler(self, sampler: str | ChunkSampler, **sampler_kwargs: Any) -> L1FlowActor:
        """The same trained network under another sampler: a new actor sharing this one's network,
        encoder and normalisers. ``sampler`` is a :class:`~l1flow_rl.flow.ChunkSampler` or a name
        (``two_step``, ``euler``, ``velocity_euler``, ``ddpm``, ``ddim``, ``direct``) with its
        keyword arguments. A sampler that reads another prediction type than the network was trained
        for is refused with :class:`~l1flow_rl.flow.samplers.SamplerMismatchError`, which lists the
        samplers that fit.

        Example:
            >>> actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(32, 64))
            >>> euler4 = actor.with_sampler("euler", steps=4)
            >>> euler4.sampler.nfe, actor.sampler.nfe, euler4.policy.net is actor.policy.net
            (4, 2, True)
        """
        new = self.policy.with_sampler(make_sampler(sampler, **sampler_kwargs))
        return type(self)(new, in_keys=self.in_keys, out_keys=self.out_keys)

    def set_sampler(self, sampler: str | ChunkSampler, **sampler_kwargs: Any) -> L1FlowActor:
        """In-place variant of :meth:`with_sampler`; returns ``self``."""
        self.policy.set_sampler(make_sampler(sampler, **sampler_kwargs))
        return self

    @classmethod
    def build(
        cls,
        encoder: ObservationEncoder,
        *,
        action_dim: int,
        obs_horizon: int = 2,
        pred_horizon: int = 16,
        action_steps: int = 8,
        network: str = DEFAULT_NETWORK,
        sampler: ChunkSampler | None = None,
        in_keys: Sequence[NestedKey] = ("observation",),
        out_keys: Sequence[NestedKey] = ("action_chunk",),
        **network_settings: Any,
    ) -> L1FlowActor:
        """Actor on the chunk denoiser ``network`` (``unet``: Diffusion Policy's ConditionalUnet1D;
        ``mlp``: an MLP over the flattened chunk) for any observation encoder. ``network_settings`` are
        the network's own (``unet``: ``down_dims``, ``timestep_embed_dim``, ``kernel_size``,
        ``n_groups``, ``timestep_scale``; ``mlp``: ``hidden_dims``, ``timestep_embed_dim``,
        ``timestep_scale``, ``activation``, ``layer_norm``, ``residual``); those not given take
        :data:`~l1flow_rl.networks.registry.NETWORKS`' defaults (the UNet's: 256/512/1024, as the paper's)."""
        sampler = sampler if sampler is not None else TwoStepSampler(0.5)
        net = make_network(
            network,
            action_dim=action_dim,
            horizon=pred_horizon,
            global_cond_dim=obs_horizon * encoder.feature_dim,
            uses_timestep=sampler.uses_timestep,
            **network_settings,
        )
        policy = ChunkPolicy(
            net,
            encoder,
            sampler,
            action_dim=action_dim,
            obs_horizon=obs_horizon,
            pred_horizon=pred_horizon,
            action_steps=action_steps,
        )
        return cls(policy, in_keys=in_keys, out_keys=out_keys)

    @classmethod
    def from_config(
        cls,
        policy_cfg: DictConfig | Mapping,
        obs_shapes: Mapping[str, Sequence[int]],
        action_dim: int,
        encoder_cfg: DictConfig | Mapping | None = None,
        network_cfg: DictConfig | Mapping | None = None,
        *,
        in_keys: Sequence[NestedKey] = ("observation",),
        out_keys: Sequence[NestedKey] = ("action_chunk",),
    ) -> L1FlowActor:
        """Actor for the policy config, the encoder config (``None``: ``auto``), the network config
        (the ``network`` group; ``None``: the UNet whose settings a ``policy`` block from before that
        group holds, the group's defaults filling the rest: ``network_config`` in
        :mod:`l1flow_rl.networks.registry`) and the dataset's observation entries (entry -> per-step
        shape: [D] flat, [3, H, W] an image).

        The encoder comes from the encoder registry (``l1flow_rl.networks.encoders``): ``auto`` takes
        ``resnet18_gn`` when an entry is an image and ``state`` otherwise; a state-only encoder on
        image entries is refused, naming them.
        """
        p = _plain(policy_cfg)
        e = _plain(encoder_cfg) if encoder_cfg is not None else {}
        name = e.pop("name", AUTO)
        net = network_config(p, None if network_cfg is None else _plain(network_cfg))
        encoder = make_encoder(name, {k: tuple(s) for k, s in obs_shapes.items()}, e)
        return cls.build(
            encoder,
            action_dim=action_dim,
            obs_horizon=p["obs_horizon"],
            pred_horizon=p["pred_horizon"],
            action_steps=p["action_steps"],
            sampler=make_sampler(p["sampler"], **p.get("sampler_kwargs", {})),
            in_keys=in_keys,
            out_keys=out_keys,
            network=net.pop("name"),
            **net,
        )

    @classmethod
    def for_state(
        cls,
        obs_dim: int | Mapping[str, int],
        action_dim: int,
        obs_horizon: int = 2,
        pred_horizon: int = 16,
        action_steps: int = 8,
        down_dims: Sequence[int] | None = None,
        **kwargs,
    ) -> L1FlowActor:
        """Actor for flat state observations.

        ``obs_dim`` is an int for a tensor observation [*B, To, D], or a mapping entry -> dim
        when the observation is a TensorDict of several flat entries. Other keyword arguments
        go to :meth:`build` (``network``, its settings, ``sampler``, ``in_keys``, ...): the default
        is the UNet (``down_dims`` None: 256/512/1024), ``network="mlp", hidden_dims=(256, 256)`` an MLP.

        Example:
            >>> mlp = L1FlowActor.for_state(obs_dim=5, action_dim=2, network="mlp", hidden_dims=(64, 64))
            >>> type(mlp.policy.net).__name__, mlp.policy.net.hidden_dims
            ('MLPDenoiser', (64, 64))
        """
        if down_dims is not None:
            kwargs["down_dims"] = down_dims
        dims = {STATE_KEY: int(obs_dim)} if isinstance(obs_dim, int) else dict(obs_dim)
        return cls.build(
            StateEncoder(dims),
            action_dim=action_dim,
            obs_horizon=obs_horizon,
            pred_horizon=pred_horizon,
            action_steps=action_steps,
            **kwargs,
        )

    # -- a folder others can load (l1flow_rl.export.pretrained) -----------------------------------------
    def save_pretrained(self, path: str | os.PathLike, **kwargs: Any) -> Path:
        """Write this actor as a pretrained folder (config.json, model.safetensors,
        normalizer.safetensors); keyword arguments as :func:`l1flow_rl.export.pretrained.save_pretrained`."""
        return pretrained_folder.write_folder(self, path, **kwargs)

    @classmethod
    def from_pretrained(cls, path: str | os.PathLike, map_location: str | Any = "cpu") -> L1FlowActor:
        """The actor a pretrained folder holds, rebuilt from its config.json alone (no hydra config)."""
        folder = Path(path)
        config = pretrained_folder.read_pretrained_config(folder)
        actor = pretrained_folder.build_described(cls, config, folder)
        pretrained_folder.load_weights(actor, pretrained_folder.read_state(folder), folder)
        return actor.to(map_location).eval()


def _plain(cfg: DictConfig | Mapping) -> dict:
    return OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)  # type: ignore[return-value]
