"""What the user gave on the command line: hydra's override list for the running command.

Some commands must tell a value the user chose from a default, e.g. ``l1flow-rl eval`` applies only
the sampler settings given on the command line onto the checkpoint's own policy config.
"""

from __future__ import annotations

from collections.abc import Sequence

from hydra.core.hydra_config import HydraConfig

__all__ = ["OPEN_DICTS", "open_dict_overrides", "overrides_under", "user_overrides"]

#: config dicts whose keys depend on another value (the sampler's or the loss's arguments): an
#: override may add a key there without hydra's ``+`` (the keys are checked against the sampler or
#: loss when the actor is built).
OPEN_DICTS = ("policy.sampler_kwargs", "policy.loss_kwargs", "eval.val_sampler_kwargs")


def user_overrides() -> list[str]:
    """The command-line overrides of the running hydra job (``hydra.overrides.task``), e.g.
    ``["policy.sampler=ddim", "policy.sampler_kwargs.steps=16"]``; empty outside a hydra job."""
    if not HydraConfig.initialized():
        return []
    return [str(o) for o in HydraConfig.get().overrides.task]


def _key(override: str) -> str:
    """The dotted key of an override (``~a.b``, ``+a.b=v``, ``++a.b=v``, ``a.b@pkg=v`` -> ``a.b``)."""
    key = override.split("=", 1)[0].lstrip("~+")
    return key.split("@", 1)[0]


def overrides_under(prefix: str, overrides: Sequence[str] | None = None) -> dict[str, str]:
    """The overrides whose key is ``prefix`` or lies under it: ``{key: override}``.

    Example:
        >>> overrides_under("policy", ["policy=ddim", "policy.sampler_kwargs.steps=8", "seed=1"])
        {'policy': 'policy=ddim', 'policy.sampler_kwargs.steps': 'policy.sampler_kwargs.steps=8'}
    """
    overrides = user_overrides() if overrides is None else overrides
    found: dict[str, str] = {}
    for o in overrides:
        key = _key(o)
        if key == prefix or key.startswith(prefix + "."):
            found[key] = o
    return found


def open_dict_overrides(overrides: Sequence[str]) -> list[str]:
    """Rewrite ``policy.sampler_kwargs.steps=16`` as ``++policy.sampler_kwargs.steps=16`` (set or add),
    so that a key the policy group's file lacks can be given as the user writes it.

    Example:
        >>> open_dict_overrides(["policy.sampler_kwargs.steps=16", "seed=1"])
        ['++policy.sampler_kwargs.steps=16', 'seed=1']
    """
    out = []
    for o in overrides:
        key = o.split("=", 1)[0]
        if "=" in o and any(key.startswith(d + ".") for d in OPEN_DICTS):
            o = "++" + o
        out.append(o)
    return out
