"""The network group (``configs/network/*.yaml``): the chunk denoiser the policy is built on.

``network=unet`` (the default; Diffusion Policy's 1-D temporal UNet, the paper's benchmarks) or
``network=mlp`` (an MLP over the flattened chunk at the RL anchors' scale, QC's and FQL's 4 x 512;
much cheaper per update on the CPU). ``timestep_embed_dim`` and ``timestep_scale`` are both networks';
the others belong to one network and are null under the other (a value there is refused, naming it).

The UNet's settings lived under ``policy.`` before this group: such an override is refused at config
time with one line naming the new key (:func:`moved_key_problems`), and a checkpoint or pretrained
folder from before still loads (its ``policy`` block's settings build the UNet).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from l1flow_rl.config.ranges import bounded

__all__ = [
    "LEGACY_POLICY_KEYS",
    "MOVED_KEYS",
    "NETWORK_FIELDS",
    "MovedKeyError",
    "NetworkConfig",
    "check_moved_keys",
    "moved_key_problems",
    "network_problems",
    "upgrade_saved_config",
]

#: the UNet settings that lived under ``policy.`` before the network group: an old checkpoint's or
#: pretrained folder's policy config still holds them
LEGACY_POLICY_KEYS = ("down_dims", "timestep_embed_dim", "kernel_size", "n_groups", "timestep_scale")
#: an override key from before the network group -> where it lives now
MOVED_KEYS = {f"policy.{k}": f"network.{k}" for k in LEGACY_POLICY_KEYS}
#: the settings each network reads (the network registry's, l1flow_rl.networks.registry.NETWORKS)
SHARED_FIELDS = ("timestep_embed_dim", "timestep_scale")
NETWORK_FIELDS = {
    "unet": (*SHARED_FIELDS, "down_dims", "kernel_size", "n_groups"),
    "mlp": (*SHARED_FIELDS, "hidden_dims", "activation", "layer_norm", "residual"),
}


@dataclass
class NetworkConfig:
    name: str = "unet"  # unet | mlp
    # sinusoidal features of t (both networks); 0 is set by itself for a sampler that reads no time
    timestep_embed_dim: int = bounded(64, ge=4)
    # t times this before the sinusoidal embedding; 1: raw t in [0, 1] as the official code
    # (see ConditionalUnet1D), 1000: Diffusion Policy's range
    timestep_scale: float = bounded(1.0, gt=0)
    # unet (null under mlp): ManiSkill's state UNet, 64/128/256 (the paper's: 256/512/1024, 128).
    down_dims: list[int] | None = bounded(lambda: [64, 128, 256], ge=1, each=True, optional=True)
    kernel_size: int | None = bounded(5, ge=1, optional=True)
    n_groups: int | None = bounded(8, ge=1, optional=True)
    # mlp (null under unet): hidden widths, QC's and FQL's 4 x 512
    hidden_dims: list[int] | None = bounded(None, ge=1, each=True, optional=True)
    activation: str | None = None  # gelu (QC, FQL) | mish
    layer_norm: bool | None = None  # LayerNorm in every hidden layer
    residual: bool | None = None  # pre-norm residual blocks instead of the plain stack


class MovedKeyError(ValueError):
    """An override names a key from before the network group; the message names the new key."""


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("~+").split("@", 1)[0]


def moved_key_problems(overrides: Iterable[str]) -> list[str]:
    """One line per override that names a moved key, with the override to write instead.

    Example:
        >>> print(*moved_key_problems(["policy.down_dims=[32,64,128]", "seed=1"]))
        policy.down_dims moved to network.down_dims (the network group): write network.down_dims=[32,64,128]
    """
    problems = []
    for o in overrides:
        new = MOVED_KEYS.get(_key(o))
        if new is not None:
            value = o.split("=", 1)[1] if "=" in o else "..."
            problems.append(f"{_key(o)} moved to {new} (the network group): write {new}={value}")
    return problems


def check_moved_keys(overrides: Sequence[str]) -> None:
    """Raise :class:`MovedKeyError` (one line) when an override names a moved key."""
    problems = moved_key_problems(overrides)
    if problems:
        raise MovedKeyError("; ".join(problems))


def network_problems(cfg: DictConfig) -> list[str]:
    """The network block against its network: settings of the other network refused (naming them),
    the UNet's widths against its GroupNorm and the chunk length against its levels."""
    net = cfg.get("network") if isinstance(cfg, DictConfig) else None
    if net is None or net.get("name") not in NETWORK_FIELDS:  # an unknown name: the choices check
        return []
    name = net.name
    own = set(NETWORK_FIELDS[name])
    problems = []
    for field in NetworkConfig.__dataclass_fields__:
        value = net.get(field)
        if field == "name" or field in own or value is None:
            continue
        owner = "|".join(n for n, fields in NETWORK_FIELDS.items() if field in fields)
        problems.append(
            f"network.{field}={_plain(value)}: a setting of network={owner}; network={name} reads "
            f"{sorted(own - set(SHARED_FIELDS))} (and {list(SHARED_FIELDS)}): set it to null or pick "
            f"network={owner}"
        )
    embed = net.get("timestep_embed_dim")
    if isinstance(embed, int) and embed % 2:
        problems.append(f"network.timestep_embed_dim={embed}: expected an even number (sin and cos halves)")
    if name == "unet" and net.get("down_dims"):
        dims, groups = list(net.down_dims), net.get("n_groups") or NetworkConfig.n_groups
        if any(d % groups for d in dims):
            problems.append(
                f"network.down_dims={dims}: every width must be divisible by network.n_groups={groups}"
            )
        multiple = 2 ** (len(dims) - 1)
        horizon = OmegaConf.select(cfg, "policy.pred_horizon", default=None)
        if horizon is not None and horizon % multiple:
            problems.append(
                f"policy.pred_horizon={horizon}: must be divisible by {multiple} "
                f"(2 ** (len(network.down_dims) - 1) for network.down_dims={dims})"
            )
    return problems


def _plain(node: Any) -> Any:
    return OmegaConf.to_container(node, resolve=True) if isinstance(node, (DictConfig, ListConfig)) else node


def upgrade_saved_config(config: dict[str, Any]) -> dict[str, Any]:
    """A saved run config (a checkpoint's) in the current layout: one from before the network group
    gets ``network`` (the UNet its ``policy`` block describes) and loses those ``policy`` keys. A
    current config is returned unchanged.

    Example:
        >>> old = {"policy": {"loss": "l1flow", "down_dims": [16, 32], "timestep_embed_dim": 16}}
        >>> new = upgrade_saved_config(old)
        >>> new["policy"], new["network"]
        ({'loss': 'l1flow'}, {'name': 'unet', 'down_dims': [16, 32], 'timestep_embed_dim': 16})
    """
    policy = config.get("policy")
    if "network" in config or not isinstance(policy, dict):
        return config
    moved = {k: policy[k] for k in LEGACY_POLICY_KEYS if k in policy}
    if not moved:
        return config
    return {
        **config,
        "policy": {k: v for k, v in policy.items() if k not in moved},
        "network": {"name": "unet", **moved},
    }
