"""The chunk denoisers a policy is built on, by name (``network.name``): ``unet`` (Diffusion Policy's
1-D temporal UNet, the default) and ``mlp`` (the RL anchors' MLP over the flattened chunk).

Both take ``(x [B, H, A], t, global_cond [B, C])`` and return [B, H, A], have the attributes the
policy checks (``action_dim``, ``global_cond_dim``, ``timestep_embed_dim``, ``horizon_multiple``) and
``settings()``, the settings that rebuild them (what a pretrained folder records).

Example:
    >>> net = make_network("mlp", action_dim=2, horizon=8, global_cond_dim=6, hidden_dims=[32, 32])
    >>> type(net).__name__, network_name(net), net.settings()["hidden_dims"]
    ('MLPDenoiser', 'mlp', [32, 32])
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

from torch import nn

from l1flow_rl.config.network import LEGACY_POLICY_KEYS, NETWORK_FIELDS, NetworkConfig
from l1flow_rl.networks.mlp import MLPDenoiser
from l1flow_rl.networks.unet1d import ConditionalUnet1D

__all__ = [
    "DEFAULT_NETWORK",
    "LEGACY_POLICY_KEYS",
    "NETWORKS",
    "NetworkSpec",
    "make_network",
    "network_config",
    "network_name",
    "network_names",
]

DEFAULT_NETWORK = "unet"


@dataclass(frozen=True)
class NetworkSpec:
    """``build(action_dim, horizon, global_cond_dim, **settings)`` makes the network; ``defaults`` are
    its settings when none are given (:meth:`L1FlowActor.build <l1flow_rl.L1FlowActor.build>` without a
    config), and name every setting it takes."""

    cls: type[nn.Module]
    build: Callable[..., nn.Module]
    defaults: Mapping[str, Any]


NETWORKS: dict[str, NetworkSpec] = {
    # the paper's network (Diffusion Policy's sizes); the state tasks' config picks 64/128/256
    "unet": NetworkSpec(
        ConditionalUnet1D,
        lambda action_dim, horizon, cond, **s: ConditionalUnet1D(action_dim, cond, **s),
        {
            "down_dims": (256, 512, 1024),
            "timestep_embed_dim": 128,
            "kernel_size": 5,
            "n_groups": 8,
            "timestep_scale": 1.0,
        },
    ),
    # QC's and FQL's flow: 4 x 512, GELU
    "mlp": NetworkSpec(
        MLPDenoiser,
        lambda action_dim, horizon, cond, **s: MLPDenoiser(action_dim, horizon, cond, **s),
        {
            "hidden_dims": (512, 512, 512, 512),
            "timestep_embed_dim": 64,
            "timestep_scale": 1.0,
            "activation": "gelu",
            "layer_norm": True,
            "residual": False,
        },
    ),
}


def network_names() -> list[str]:
    return sorted(NETWORKS)


def network_name(net: nn.Module) -> str:
    """The registered name of a network's class."""
    for name, spec in NETWORKS.items():
        if type(net) is spec.cls:
            return name
    raise ValueError(f"{type(net).__name__} is not a registered network ({network_names()})")


def make_network(
    name: str,
    *,
    action_dim: int,
    horizon: int,
    global_cond_dim: int,
    uses_timestep: bool = True,
    **settings: Any,
) -> nn.Module:
    """The network ``name`` for chunks [H=horizon, A=action_dim] and a condition of
    ``global_cond_dim``; settings not given (or None) take the network's defaults. Without
    ``uses_timestep`` (a sampler that reads no time, as regression's) it is built timestep-free."""
    if name not in NETWORKS:
        raise ValueError(f"network {name!r}: expected one of {network_names()}")
    spec = NETWORKS[name]
    unknown = sorted(k for k, v in settings.items() if k not in spec.defaults and v is not None)
    if unknown:
        raise ValueError(f"network {name!r} takes no setting {unknown}; it takes {sorted(spec.defaults)}")
    given = {k: v for k, v in settings.items() if v is not None}
    merged = {**spec.defaults, **given}
    if not uses_timestep:
        merged["timestep_embed_dim"] = 0
    return spec.build(action_dim, horizon, global_cond_dim, **merged)


def network_config(policy: Mapping[str, Any], network: Mapping[str, Any] | None) -> dict[str, Any]:
    """``{"name": ..., **settings}`` of the network a config describes: its ``network`` block (unset
    settings dropped), or for a policy config from before that group (``network`` None) the UNet
    whose settings its ``policy`` block holds, the network group's defaults
    (:class:`~l1flow_rl.config.NetworkConfig`) filling those it lacks. A policy config that holds no
    network setting and no network block is refused: today's config keeps the network in its
    ``network`` block, and building the default UNet in its place would ignore what that block says.

    Example:
        >>> network_config({"down_dims": [16, 32], "timestep_embed_dim": 16}, None)["down_dims"]
        [16, 32]
        >>> network_config({}, {"name": "mlp", "hidden_dims": [64], "down_dims": None})
        {'name': 'mlp', 'hidden_dims': [64]}
    """
    if network is not None:
        out = {k: v for k, v in dict(network).items() if v is not None}
        out.setdefault("name", DEFAULT_NETWORK)
        return out
    legacy = {k: policy[k] for k in LEGACY_POLICY_KEYS if policy.get(k) is not None}
    if not legacy:
        raise ValueError(
            "no network settings: the network is the network config group (network=unet|mlp); pass its "
            "block too (build_actor(cfg.policy, shapes, action_dim, cfg.encoder, cfg.network))"
        )
    defaults = asdict(NetworkConfig())
    return {"name": DEFAULT_NETWORK, **{k: defaults[k] for k in NETWORK_FIELDS["unet"]}, **legacy}
