"""Evaluation protocols: named recipes that fix how a figure is measured, so it can be compared with
a published one.

A protocol may set the test episodes and seeds, task fields of the evaluation env (e.g. ManiSkill's
per-task ``max_episode_steps``), env options (``reconfigure_each_episode``), the simulation backend
and the headline metric. ``eval.protocol=NAME`` picks one; a value the user gives on the command
line (``eval.episodes=20``) still wins and is recorded in eval.json as a deviation.

Built in: ``default`` (this project's settings: the task config as is, ``eval.*`` as configured) and
``maniskill`` (ManiSkill's Diffusion Policy baseline evaluation). A simulator package registers its
own (PushT: ``diffusion_policy``) with :func:`register_protocol`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from l1flow_rl.config import TaskConfig

__all__ = [
    "EvalProtocol",
    "get_protocol",
    "maniskill_baseline_steps",
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
    if protocol.name in _REGISTRY and not replace and _REGISTRY[protocol.name] is not protocol:
        raise ValueError(f"an evaluation protocol named {protocol.name!r} is already registered")
    _REGISTRY[protocol.name] = protocol
    return protocol


def _load_simulator_protocols() -> None:
    # simulator packages register their own protocols when imported (they import no simulator)
    from l1flow_rl.envs.registry import registered_simulators

    registered_simulators()


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


#: max_episode_steps of ManiSkill's Diffusion Policy baseline (examples/baselines/diffusion_policy),
#: by env id; other tasks run to the env's own registered limit there
MANISKILL_BASELINE_STEPS: dict[str, int] = {
    "PushCube-v1": 100,
    "PickCube-v1": 100,
    "StackCube-v1": 200,
    "PegInsertionSide-v1": 300,
}


def maniskill_baseline_steps(task: TaskConfig) -> dict[str, Any]:
    """``max_episode_steps`` as ManiSkill's baseline sets it for ``task.env_id``: the table above,
    else the env's registered default (ManiSkill is imported only for such a task)."""
    steps = MANISKILL_BASELINE_STEPS.get(task.env_id)
    if steps is None:
        import gymnasium as gym
        import mani_skill.envs  # noqa: F401  (registers the env ids)

        try:
            steps = gym.spec(task.env_id).max_episode_steps
        except gym.error.Error as err:
            raise ValueError(f"eval.protocol=maniskill: unknown ManiSkill env id {task.env_id!r}") from err
        if steps is None:
            raise ValueError(f"eval.protocol=maniskill: {task.env_id!r} registers no max_episode_steps")
    return {"max_episode_steps": int(steps)}


register_protocol(
    EvalProtocol(
        name="default",
        description="this project's settings: the task config's episode limit, eval.episodes and eval.seed",
    )
)
register_protocol(
    EvalProtocol(
        name="maniskill",
        description=(
            "ManiSkill's Diffusion Policy baseline: its per-task max_episode_steps, 100 episodes, "
            "physx_cpu, scene reconfigured each episode, success_once first"
        ),
        episodes=100,
        task_fields=maniskill_baseline_steps,
        env_options={"reconfigure_each_episode": True},
        env_device="cpu",
        headline="success_once",
        simulators=("maniskill",),
    )
)
