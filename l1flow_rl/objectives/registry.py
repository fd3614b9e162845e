"""The ``policy.loss`` registry: a loss's name in the config -> its class, and what its options
(``policy.loss_kwargs``) may hold.

A new behaviour-cloning loss is one module (a :class:`~l1flow_rl.objectives.ChunkLossBase`
subclass) plus one :func:`register_loss` call; the config validator and the training job find it
here.

Example:
    >>> loss_names()
    ['consistency', 'diffusion', 'edm', 'flow_matching', 'l1flow', 'onedp_d', 'onedp_s', 'regression']
    >>> loss_problems("l1flow", {"timestep": "mixed"})  # doctest: +ELLIPSIS
    ["policy.loss_kwargs.timestep: loss 'l1flow' (L1FlowLoss) takes no such argument; it takes [...]"]
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any

from torchrl.objectives import LossModule

from l1flow_rl.flow.timesteps import make_timesteps
from l1flow_rl.objectives.consistency import ConsistencyLoss
from l1flow_rl.objectives.diffusion import DiffusionLoss
from l1flow_rl.objectives.edm import EDMLoss
from l1flow_rl.objectives.flow_matching import FlowMatchingLoss
from l1flow_rl.objectives.l1flow import L1FlowLoss
from l1flow_rl.objectives.onedp_d import OneDPDLoss
from l1flow_rl.objectives.onedp_s import OneDPSLoss
from l1flow_rl.objectives.regression import RegressionLoss

__all__ = ["LOSSES", "get_loss", "loss_names", "loss_problems", "register_loss"]

#: name -> loss class; read through :func:`get_loss` and :func:`loss_names`
LOSSES: dict[str, type[LossModule]] = {}


def register_loss(name: str, cls: type[LossModule], *, replace: bool = False) -> type[LossModule]:
    """Make ``cls`` the loss of ``policy.loss=<name>``; a second one under the same name is an
    error unless ``replace``."""
    if name in LOSSES and not replace and LOSSES[name] is not cls:
        raise ValueError(f"a loss named {name!r} is already registered ({LOSSES[name].__name__})")
    LOSSES[name] = cls
    return cls


def loss_names() -> list[str]:
    return sorted(LOSSES)


def get_loss(name: str) -> type[LossModule]:
    try:
        return LOSSES[name]
    except KeyError:
        raise ValueError(f"policy.loss={name!r} is not one of {loss_names()}") from None


def _accepted_kwargs(cls: type) -> list[str]:
    params = inspect.signature(cls.__init__).parameters.values()
    skip = {"self", "actor_network"}
    skip.add("teacher")  # a distillation loss's teacher comes from the top-level teacher=, not loss_kwargs
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return [p.name for p in params if p.name not in skip and p.kind in kinds]


def loss_problems(name: str, kwargs: Mapping[str, Any] | None, prefix: str = "policy") -> list[str]:
    """What is wrong with loss ``name``'s keyword arguments, one line each naming
    ``<prefix>.loss_kwargs.<key>``: arguments its constructor does not take, and a timestep law
    (``timesteps``) that does not exist. Nothing is built."""
    cls = get_loss(name)
    accepted = _accepted_kwargs(cls)
    kwargs = dict(kwargs or {})
    problems = [
        f"{prefix}.loss_kwargs.{k}: loss {name!r} ({cls.__name__}) takes no such argument; "
        f"it takes {accepted}"
        for k in sorted(set(kwargs) - set(accepted))
    ]
    if isinstance(kwargs.get("timesteps"), str):
        try:
            make_timesteps(kwargs["timesteps"])
        except ValueError as err:
            problems.append(f"{prefix}.loss_kwargs.timesteps: {err}")
    return problems


register_loss("l1flow", L1FlowLoss)
register_loss("flow_matching", FlowMatchingLoss)
register_loss("diffusion", DiffusionLoss)
register_loss("regression", RegressionLoss)
register_loss("edm", EDMLoss)
register_loss("consistency", ConsistencyLoss)
register_loss("onedp_d", OneDPDLoss)
register_loss("onedp_s", OneDPSLoss)
