"""Turn validated :class:`~l1flow_rl.config.PolicyConfig` and
:class:`~l1flow_rl.config.EncoderConfig` into an actor, and the policy config into its loss."""

from __future__ import annotations

from collections.abc import Mapping

from omegaconf import DictConfig, OmegaConf
from torchrl.objectives import LossModule

from l1flow_rl.actor import L1FlowActor
from l1flow_rl.flow.samplers import make_sampler
from l1flow_rl.networks.encoders import AUTO, make_encoder
from l1flow_rl.objectives.registry import get_loss

__all__ = ["build_actor", "build_loss"]


def _plain(cfg: DictConfig | Mapping) -> dict:
    return OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)  # type: ignore[return-value]


def build_actor(
    policy_cfg: DictConfig | Mapping,
    obs_shapes: Mapping[str, tuple[int, ...]],
    action_dim: int,
    encoder_cfg: DictConfig | Mapping | None = None,
) -> L1FlowActor:
    """Actor for the policy config, the encoder config (``None``: ``auto``) and the dataset's
    observation entries (entry -> per-step shape: [D] flat, [3, H, W] an image).

    The encoder comes from the encoder registry (``l1flow_rl.networks.encoders``): ``auto`` takes
    ``resnet18_gn`` when an entry is an image and ``state`` otherwise; a state-only encoder on
    image entries is refused, naming them.
    """
    p = _plain(policy_cfg)
    e = _plain(encoder_cfg) if encoder_cfg is not None else {}
    name = e.pop("name", AUTO)
    encoder = make_encoder(name, {k: tuple(s) for k, s in obs_shapes.items()}, e)
    return L1FlowActor.build(
        encoder,
        action_dim=action_dim,
        obs_horizon=p["obs_horizon"],
        pred_horizon=p["pred_horizon"],
        action_steps=p["action_steps"],
        down_dims=tuple(p["down_dims"]),
        timestep_embed_dim=p["timestep_embed_dim"],
        kernel_size=p["kernel_size"],
        n_groups=p["n_groups"],
        timestep_scale=p.get("timestep_scale", 1.0),  # checkpoints from before the field: raw t
        sampler=make_sampler(p["sampler"], **p.get("sampler_kwargs", {})),
    )


def build_loss(actor: L1FlowActor, policy_cfg: DictConfig | Mapping) -> LossModule:
    p = _plain(policy_cfg)
    return get_loss(p["loss"])(actor, **p.get("loss_kwargs", {}))
