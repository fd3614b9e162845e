"""Re-scoring a trained network under another sampler from the command line.

``l1flow-rl eval checkpoint=CKPT policy.sampler=ddim policy.sampler_kwargs.steps=16``: the
checkpoint's own policy config is the base, and only the sampler settings given on the command line
apply. Settings of the checkpoint's sampler that the new sampler also takes carry over (a DDPM
network's ``num_train_timesteps`` for DDIM). ``policy=NAME`` takes that policy file's sampler
settings. Anything else under ``policy.`` is refused: the network comes from the checkpoint.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from omegaconf import DictConfig, OmegaConf

from l1flow_rl.config.overrides import overrides_under
from l1flow_rl.flow.samplers import sampler_parameters

__all__ = ["eval_sampler"]

_SAMPLER, _KWARGS = "policy.sampler", "policy.sampler_kwargs"


def _plain(node: DictConfig | Mapping[str, Any]) -> dict[str, Any]:
    return OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node)  # type: ignore[return-value]


def eval_sampler(
    saved_policy: DictConfig | Mapping[str, Any],
    composed_policy: DictConfig | Mapping[str, Any],
    overrides: Sequence[str] | None = None,
) -> tuple[str, dict[str, Any]]:
    """The sampler (name, kwargs) to evaluate a checkpoint with.

    Args:
        saved_policy: the checkpoint's ``policy`` config.
        composed_policy: the command's composed ``policy`` config (holds the user's values).
        overrides: the command line's overrides (default: the running hydra job's).

    Example:
        >>> saved = {"sampler": "ddpm", "sampler_kwargs": {"num_train_timesteps": 100}}
        >>> composed = {"sampler": "ddim", "sampler_kwargs": {"t_first": 0.5, "steps": 16}}
        >>> eval_sampler(saved, composed, ["policy.sampler=ddim", "policy.sampler_kwargs.steps=16"])
        ('ddim', {'num_train_timesteps': 100, 'steps': 16})
    """
    saved, composed = _plain(saved_policy), _plain(composed_policy)
    given = overrides_under("policy", overrides)
    sampler_keys = ("policy", _SAMPLER, _KWARGS)
    others = [k for k in given if k not in sampler_keys and not k.startswith(_KWARGS + ".")]
    if others:
        raise ValueError(
            f"l1flow-rl eval takes the network from the checkpoint; only policy.sampler and "
            f"policy.sampler_kwargs.* (or policy=NAME for its sampler) may be given, not {others}"
        )
    saved_kwargs = dict(saved.get("sampler_kwargs") or {})
    if not given:
        return saved["sampler"], saved_kwargs
    if "policy" in given:  # a policy file: its sampler settings, with the user's own on top
        return composed["sampler"], dict(composed.get("sampler_kwargs") or {})
    name = composed["sampler"] if _SAMPLER in given else saved["sampler"]
    if name != saved["sampler"]:
        accepted = set(sampler_parameters(name))
        kwargs = {k: v for k, v in saved_kwargs.items() if k in accepted}
    else:
        kwargs = saved_kwargs
    user_kwargs = dict(composed.get("sampler_kwargs") or {})
    for key, override in given.items():
        deleted = override.startswith("~")
        if key == _KWARGS:
            kwargs = {} if deleted else user_kwargs
        elif key.startswith(_KWARGS + "."):
            sub = key.split(".")[2]
            if deleted:
                kwargs.pop(sub, None)
            else:
                kwargs[sub] = user_kwargs[sub]
    return name, kwargs
