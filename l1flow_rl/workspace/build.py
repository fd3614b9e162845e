"""Turn validated :class:`~l1flow_rl.config.PolicyConfig`, :class:`~l1flow_rl.config.EncoderConfig` and
:class:`~l1flow_rl.config.NetworkConfig` into an actor, and the policy config into its loss."""

from __future__ import annotations

from collections.abc import Mapping

from omegaconf import DictConfig, OmegaConf
from torchrl.objectives import LossModule

from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.objectives.registry import get_loss

__all__ = ["build_actor", "build_loss", "padding_masked_by_default"]


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


def padding_masked_by_default(control: str | None) -> bool:
    """Whether a chunk loss leaves padded steps out unless ``policy.loss_kwargs.mask_padding`` says.

    Delta control pads past an episode's end with "no motion", a label the demonstrator never gave
    mid-task: trained on, it teaches the policy to stop early (the main job's pushes that halt after
    5-8 cm). Absolute control pads with the last action, which is what holding still means, so those
    steps stay in the loss as in Diffusion Policy."""
    return control == "delta"


def build_loss(
    actor: L1FlowActor, policy_cfg: DictConfig | Mapping, *, control: str | None = None, **extra
) -> LossModule:
    """The policy config's loss on ``actor``; ``control`` is the data's control kind (``task.control``),
    which sets ``mask_padding`` where ``policy.loss_kwargs`` does not
    (:func:`padding_masked_by_default`); ``extra`` are arguments that do not come from
    ``policy.loss_kwargs`` (a distillation loss's ``teacher``)."""
    p = _plain(policy_cfg)
    kwargs = {"mask_padding": padding_masked_by_default(control), **p.get("loss_kwargs", {})}
    return get_loss(p["loss"])(actor, **kwargs, **extra)
