"""Turn validated :class:`~l1flow_rl.config.PolicyConfig`, :class:`~l1flow_rl.config.EncoderConfig` and
:class:`~l1flow_rl.config.NetworkConfig` into an actor, and the policy config into its loss."""

from __future__ import annotations

from collections.abc import Mapping

from omegaconf import DictConfig, OmegaConf
from torchrl.objectives import LossModule

from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.objectives.registry import get_loss

__all__ = ["build_actor", "build_loss"]


def _plain(cfg: DictConfig | Mapping) -> dict:
    return OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)  # type: ignore[return-value]


def build_actor(
    policy_cfg: DictConfig | Mapping,
    obs_shapes: Mapping[str, tuple[int, ...]],
    action_dim: int,
    encoder_cfg: DictConfig | Mapping | None = None,
    network_cfg: DictConfig | Mapping | None = None,
) -> L1FlowActor:
    """Actor for the policy config, the encoder config (``None``: ``auto``), the network config (the
    ``network`` group) and the dataset's observation entries:
    :meth:`L1FlowActor.from_config <l1flow_rl.L1FlowActor.from_config>`."""
    return L1FlowActor.from_config(policy_cfg, obs_shapes, action_dim, encoder_cfg, network_cfg)


def build_loss(actor: L1FlowActor, policy_cfg: DictConfig | Mapping, **extra) -> LossModule:
    """The policy config's loss on ``actor``; ``extra`` are arguments that do not come from
    ``policy.loss_kwargs`` (a distillation loss's ``teacher``)."""
    p = _plain(policy_cfg)
    return get_loss(p["loss"])(actor, **p.get("loss_kwargs", {}), **extra)
