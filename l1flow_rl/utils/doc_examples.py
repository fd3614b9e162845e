"""The runnable docstring examples that several classes share, kept once and appended to each.

The fine-tuning losses and actors all start from the same small flow, chunk critic and batch of
chunk transitions, and the behaviour-cloning losses differ only in their sampler: writing each
example out per class kept drifting copies. :func:`add_example` appends ``Examples:`` to a class
docstring (``doctest`` and ``help`` read ``__doc__``, so the example runs and shows as written).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

__all__ = [
    "CRITIC",
    "FLOW",
    "TRAIN_STEP",
    "TRANSITIONS",
    "add_example",
    "chunk_loss_example",
    "distillation_example",
]

T = TypeVar("T")

#: A 2-D state flow (``flow``) and the imports every fine-tuning example uses.
FLOW = """\
>>> import torch
>>> from tensordict import TensorDict
>>> from l1flow_rl import L1FlowActor
>>> from l1flow_rl.networks.critic import ChunkCritic
>>> flow = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
"""

#: A chunk critic (``critic``) over the flow's first 8 executed actions.
CRITIC = """\
>>> critic = ChunkCritic.from_policy(flow, input_shape=(8, 2), hidden_dims=(32,))
"""

#: A batch of 4 chunk transitions (``td``) with the keys :class:`~l1flow_rl.ChunkCriticLoss` reads.
TRANSITIONS = """\
>>> td = TensorDict({"observation": torch.randn(4, 2, 5), "action_chunk": torch.rand(4, 16, 2),
...                  "next": {"observation": torch.randn(4, 2, 5), "reward": torch.rand(4, 1),
...                           "terminated": torch.zeros(4, 1, dtype=torch.bool)}}, [4])
"""

#: One optimisation step of ``loss_fn`` on ``td``: every ``loss_*`` term, then the target update.
TRAIN_STEP = """\
>>> from torchrl.objectives import SoftUpdate
>>> out = loss_fn(td)
>>> sum(v for k, v in out.items() if k.startswith("loss_")).backward()
>>> SoftUpdate(loss_fn, tau=0.005).step()
"""


def add_example(*parts: str) -> Callable[[T], T]:
    """A class decorator appending ``Examples:`` made of ``parts`` (doctest lines, unindented)."""

    def decorate(obj: T) -> T:
        if obj.__doc__ is not None:  # None under ``python -OO``
            lines = "".join(parts).splitlines()
            body = "\n".join(f"        {line}" for line in lines)
            obj.__doc__ = f"{obj.__doc__.rstrip()}\n\n    Examples:\n{body}\n    "
        return obj

    return decorate


def chunk_loss_example(sampler: str) -> Callable[[T], T]:
    """``add_example`` for a behaviour-cloning loss trained with an actor sampling by ``sampler``
    (a :mod:`l1flow_rl.flow` constructor call): build it, compute the loss on a batch, backward."""

    def decorate(cls: T) -> T:
        name, loss_key = cls.__name__, cls.loss_name  # type: ignore[attr-defined]
        sampler_class = sampler.partition("(")[0]
        return add_example(
            ">>> import torch\n"
            ">>> from tensordict import TensorDict\n"
            f">>> from l1flow_rl import L1FlowActor, {name}\n"
            f">>> from l1flow_rl.flow import {sampler_class}\n"
            ">>> actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(32, 64),\n"
            f"...                               sampler={sampler})\n"
            '>>> td = TensorDict({"observation": torch.randn(4, 2, 5),\n'
            '...                  "action_chunk": torch.rand(4, 16, 2) * 2 - 1}, batch_size=[4])\n'
            f'>>> {name}(actor)(td)["{loss_key}"].backward()\n'
        )(cls)

    return decorate


def distillation_example(teacher: str, student: str, nfe: int, *, scale: float = 1000.0) -> Callable[[T], T]:
    """``add_example`` for a distillation loss: a teacher sampling by ``teacher`` and a student by
    ``student`` (:mod:`l1flow_rl.flow` constructor calls) on one network shape with time scale
    ``scale``; compute the loss on a batch, backward, and show the student's NFE (``nfe``)."""

    def decorate(cls: T) -> T:
        name, loss_key = cls.__name__, cls.loss_name  # type: ignore[attr-defined]
        classes = sorted({teacher.partition("(")[0], student.partition("(")[0]})
        return add_example(
            ">>> import torch\n"
            ">>> from tensordict import TensorDict\n"
            f">>> from l1flow_rl import L1FlowActor, {name}\n"
            f">>> from l1flow_rl.flow import {', '.join(classes)}\n"
            ">>> make = lambda sampler: L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32),\n"
            f"...                                              sampler=sampler, timestep_scale={scale})\n"
            f">>> loss_fn = {name}(make({student}), teacher=make({teacher}))\n"
            '>>> td = TensorDict({"observation": torch.randn(4, 2, 5),\n'
            '...                  "action_chunk": torch.rand(4, 16, 2) * 2 - 1}, batch_size=[4])\n'
            f'>>> loss_fn(td)["{loss_key}"].backward()\n'
            ">>> loss_fn.policy.sampler.nfe\n"
            f"{nfe}\n"
        )(cls)

    return decorate
