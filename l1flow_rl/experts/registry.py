"""The demonstration-source registry: one expert (scripted policy or planner) per simulator.

An expert is registered by a package ``l1flow_rl.experts.<simulator>`` (imported on first use, so it
imports no simulator until demonstrations are made) or by any user module calling
:func:`register_expert`. ``ensure_demos`` and ``l1flow-rl demos`` dispatch through it.

The contract: ``make(task, num, data_dir, seed=..., **options) -> Path`` returns a file or directory
that :func:`l1flow_rl.data.load_episodes` reads, holding ``num`` successful demonstrations of
``task`` with rewards, termination flags and the observation after each episode's last action (so
that a critic can learn from them; ``episodes_metadata`` reports what a file records), recorded in
the task's control mode, generating only what its cache under ``data_dir`` lacks (idempotent,
resumable, atomic: a half-written dataset never carries the final name).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from l1flow_rl.utils.registries import register_unique

if TYPE_CHECKING:  # pragma: no cover
    from l1flow_rl.config import TaskConfig

__all__ = [
    "DemoGenerationError",
    "ExpertSpec",
    "ensure_demos",
    "get_expert",
    "register_expert",
    "registered_experts",
]


def builtin_experts() -> list[str]:
    """The expert packages under ``l1flow_rl.experts`` (found on disk, so adding one edits nothing
    here); a package elsewhere registers itself on import (``register_expert`` is public)."""
    return sorted(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)]) if m.ispkg)


class DemoGenerationError(RuntimeError):
    """An expert could not make the demonstrations asked for; the message says what failed."""


@dataclass(frozen=True)
class ExpertSpec:
    """How to make demonstrations for the tasks of one simulator.

    Args:
        simulator: the ``TaskConfig.simulator`` it serves.
        make: ``(task, num, data_dir, *, seed, **options) -> Path`` (see the module docstring), or
            ``"package.module:function"`` naming it, imported only when demonstrations are made.
        description: one line for ``l1flow-rl demos --help`` and error messages.
        env_ids: the env ids it can solve (empty: all of the simulator's).
        options: keyword options ``make`` accepts beyond ``seed`` (from ``demos`` and ``task.expert``).
    """

    simulator: str
    make: Callable[..., Path] | str
    description: str
    env_ids: tuple[str, ...] = ()
    options: tuple[str, ...] = ()

    def maker(self) -> Callable[..., Path]:
        """``make`` itself, or the function a ``"package.module:function"`` string names, imported
        now: a built-in expert imports its simulator only when demonstrations are made."""
        if callable(self.make):
            return self.make
        module, _, name = self.make.partition(":")
        return getattr(importlib.import_module(module), name)

    def supports(self, task: TaskConfig) -> bool:
        return not self.env_ids or task.env_id in self.env_ids


_REGISTRY: dict[str, ExpertSpec] = {}


def register_expert(spec: ExpertSpec, *, replace: bool = False) -> ExpertSpec:
    return register_unique(_REGISTRY, spec.simulator, spec, replace=replace, what="an expert for simulator")


def unregister_expert(simulator: str) -> None:
    _REGISTRY.pop(simulator, None)


def _load_builtins() -> None:
    for name in builtin_experts():
        if name not in _REGISTRY and importlib.util.find_spec(f"l1flow_rl.experts.{name}") is not None:
            importlib.import_module(f"l1flow_rl.experts.{name}")


def registered_experts() -> dict[str, ExpertSpec]:
    _load_builtins()
    return dict(_REGISTRY)


def get_expert(task: TaskConfig) -> ExpertSpec:
    """The expert for ``task``'s simulator; an error says which experts exist and how to bring data."""
    if task.simulator not in _REGISTRY:
        _load_builtins()
    spec = _REGISTRY.get(task.simulator)
    if spec is None:
        raise DemoGenerationError(
            f"task {task.name!r}: no expert makes demonstrations for simulator {task.simulator!r} "
            f"(experts exist for {sorted(_REGISTRY)}); point data.path at your own demonstration file"
        )
    if not spec.supports(task):
        raise DemoGenerationError(
            f"task {task.name!r}: the {task.simulator} expert solves {list(spec.env_ids)}, not "
            f"{task.env_id!r}; point data.path at your own demonstration file"
        )
    return spec


def ensure_demos(
    task: TaskConfig, num: int, data_dir: str | os.PathLike, seed: int = 0, **options: Any
) -> Path:
    """Path of a dataset with ``num`` successful demonstrations of ``task``, made by its simulator's
    expert where the cache under ``data_dir`` lacks them. ``options`` go to the expert; options the
    expert does not take are refused, naming them.

    Example:
        >>> from l1flow_rl.config import load_task_config
        >>> path = ensure_demos(load_task_config("maniskill_pushcube"), 3, "data")  # doctest: +SKIP
    """
    spec = get_expert(task)
    options = {**task.expert, **options}
    unknown = sorted(set(options) - set(spec.options))
    if unknown:
        raise TypeError(
            f"task {task.name!r}: the {spec.simulator} expert takes no option(s) {unknown} "
            f"(it takes {list(spec.options)})"
        )
    return Path(spec.maker()(task, num, data_dir, seed=seed, **options))
