"""Evaluation protocols: named recipes that fix how a figure is measured, so it can be compared with
a published one.

A protocol may set the test episodes and seeds, task fields of the evaluation env (e.g. ManiSkill's
per-task ``max_episode_steps``), env options (``reconfigure_each_episode``), the simulation backend
and the headline metric. ``eval.protocol=NAME`` picks one; a value the user gives on the command
line (``eval.episodes=20``) still wins and is recorded in eval.json as a deviation.

Built in: ``default`` (this project's settings: the task config as is, ``eval.*`` as configured). A
simulator's own protocols live beside it and register themselves with :func:`register_protocol`
when its package is imported: ``maniskill`` (ManiSkill's Diffusion Policy baseline evaluation,
``envs/maniskill/protocol.py``), ``diffusion_policy`` (PushT, ``envs/pusht/protocol.py``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from l1flow_rl.config import TaskConfig
from l1flow_rl.envs.registry import registered_simulators
from l1flow_rl.utils.registries import register_unique

__all__ = [
    "EvalProtocol",
    "get_protocol",
    "protocol_names",
    "register_protocol",
]


@dataclass(frozen=True)
class EvalProtocol:
    """How an evaluation is run and what it reports first.

    Args:
        name: the value of ``eval.protocol`` that selects it.
        description: one line for eval.json and ``--help``.
        episodes: test episodes (None: ``eval.episodes``).
        seed: the first test seed (None: ``eval.seed``).
        task_fields: ``task -> {TaskConfig field: value}`` for the evaluation env (training data
            is unaffected), e.g. ``max_episode_steps``; may raise for a task it cannot serve.
        env_options: ``make_env`` options of the evaluation env (the simulator's own, e.g.
            ``reconfigure_each_episode``).
        env_device: ``"cpu"`` runs the simulator on its CPU backend whatever the policy's device
            (ManiSkill: physx_cpu); None: the run's device.
        headline: the metric reported first and used to pick the best checkpoint.
        simulators: the simulators it applies to (None: any).
    """

    name: str
    description: str
    episodes: int | None = None
    seed: int | None = None
    task_fields: Callable[[TaskConfig], Mapping[str, Any]] | None = None
    env_options: Mapping[str, Any] = field(default_factory=dict)
    env_device: str | None = None
    headline: str = "success_once"
    simulators: tuple[str, ...] | None = None

    def check_task(self, task: TaskConfig) -> None:
        if self.simulators is not None and task.simulator not in self.simulators:
            raise ValueError(
                f"eval.protocol={self.name!r} applies to simulators {list(self.simulators)}; task "
                f"{task.name!r} runs on {task.simulator!r}"
            )

    def eval_task(self, task: TaskConfig) -> TaskConfig:
        """The task config of the evaluation env under this protocol."""
        self.check_task(task)
        fields = dict(self.task_fields(task)) if self.task_fields is not None else {}
        return dataclasses.replace(task, **fields) if fields else task

    def record(self) -> dict[str, Any]:
        """What eval.json says about the protocol itself."""
        return {
            "name": self.name,
            "description": self.description,
            "env_options": dict(self.env_options),
            "env_device": self.env_device,
            "headline": self.headline,
        }


_REGISTRY: dict[str, EvalProtocol] = {}


def register_protocol(protocol: EvalProtocol, *, replace: bool = False) -> EvalProtocol:
    """Add a protocol; a second one under the same name is an error unless ``replace``."""
    return register_unique(
        _REGISTRY, protocol.name, protocol, replace=replace, what="an evaluation protocol named"
    )


def _load_simulator_protocols() -> None:
    registered_simulators()  # simulator packages register their own protocols when imported


def protocol_names() -> list[str]:
    _load_simulator_protocols()
    return sorted(_REGISTRY)


def get_protocol(name: str) -> EvalProtocol:
    """The protocol registered under ``name``; an unknown name lists the known ones."""
    if name not in _REGISTRY:
        _load_simulator_protocols()
    try:
        return _REGISTRY[name]
    except KeyError:
        known = sorted(_REGISTRY)
        raise ValueError(f"unknown eval.protocol {name!r}; registered protocols: {known}") from None


register_protocol(
    EvalProtocol(
        name="default",
        description="this project's settings: the task config's episode limit, eval.episodes and eval.seed",
    )
)
