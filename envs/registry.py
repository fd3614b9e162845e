"""The simulator registry: what ``make_env`` needs to know about a simulator, and nothing else.

A simulator is one package under ``envs/`` (``envs/maniskill/``, ``envs/robosuite/``, ...) that calls
:func:`register_simulator` in its ``__init__`` without importing the simulator itself. Its task
configs (``configs/task/*.yaml``) name it in ``simulator:``. Adding a simulator touches its own
package and its task configs only: ``make_env``, the trainer and the evaluator look it up here.

The env contract (what the trainer, the evaluator and the tests rely on). ``factory(task, num_envs,
device, **options)`` returns a TorchRL ``EnvBase`` of batch size ``[num_envs]`` whose step and reset
outputs hold

================================ ====================================================================
``"observation"``                float32 [N, D] (state tasks), or a TensorDict of named entries:
                                 ``"state"`` float32 [N, D] and images uint8 [N, 3, H, W] named by
                                 camera (``"rgb"`` for a single camera)
``"reward"``                     float32 [N, 1]
``"done"``/``"terminated"``/     bool [N, 1]
``"truncated"``
``"success"``                    bool [N, 1], the simulator's own success signal
``"sim_error"`` (optional)       bool [N, 1], True when a simulator error ended the episode
================================ ====================================================================

and supports per-env seeded partial resets (``reset(tensordict with "_reset", seed=[...])``, or
``list_of_kwargs`` for worker envs), ``render_frames()`` (uint8 [N, H, W, 3]) when made with
``render=True``, and ``sim_error_message()`` when it reports ``"sim_error"``. Extra per-step entries
(PushT's ``"coverage"``, ...) are allowed and reach the evaluator's per-step hook.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from tensordict.utils import NestedKey

if TYPE_CHECKING:  # pragma: no cover
    import torch
    from torchrl.envs import EnvBase

    from l1flow_rl.config import TaskConfig

__all__ = [
    "SimulatorNotInstalledError",
    "SimulatorSpec",
    "get_simulator",
    "register_simulator",
    "registered_simulators",
]

#: Packages under ``l1flow_rl.envs`` that register a simulator when imported. A package outside this
#: list registers itself on import (``register_simulator`` is public), e.g. a user's own adapter.
BUILTIN_SIMULATORS: tuple[str, ...] = ("maniskill", "robosuite", "pusht")


class SimulatorNotInstalledError(ImportError):
    """The simulator a task needs is not importable; the message says how to install it."""


@dataclass(frozen=True)
class SimulatorSpec:
    """How to make and read one simulator's TorchRL env.

    Args:
        name: the value of ``TaskConfig.simulator`` that selects it.
        factory: ``(task, num_envs, device, **options) -> EnvBase`` of batch ``[num_envs]`` (see the
            module docstring for the outputs). ``options`` are ``make_env``'s keyword arguments
            (``ignore_terminations``, ``render``, ``camera``, ...) plus the task's ``env`` block;
            a factory refuses options it does not know, naming them.
        observation_entries: ``task -> {entry: frame_dims}``, the observation entries of one step
            and the number of dims of one frame (1 for a vector, 3 for an image [3, H, W]), so the
            history transforms know where to stack To frames. The entry is ``"observation"`` for
            a flat state or ``("observation", name)`` for the entries of a TensorDict observation.
        install_hint: what to run when the simulator is missing.
        requires: importable module names the simulator needs (checked by :meth:`check_installed`
            without importing them).
        obs_modes: the ``TaskConfig.obs_mode`` values it supports.
        success_key: the output entry that holds its success signal.
        options: extra keyword arguments its factory accepts (validated at config time).
        episode_metrics: extra per-episode metrics the evaluator reports (mean and 95 % interval
            over episodes): ``name -> (reduction, step entry)``, reduction one of ``"max"``,
            ``"sum"``, ``"last"``, ``"any"`` over the episode's steps; e.g. PushT's Diffusion Policy
            score ``{"score": ("max", "reward")}``.
    """

    name: str
    factory: Callable[..., EnvBase]
    observation_entries: Callable[[TaskConfig], Mapping[NestedKey, int]]
    install_hint: str
    requires: tuple[str, ...] = ()
    obs_modes: tuple[str, ...] = ("state",)
    success_key: NestedKey = "success"
    options: tuple[str, ...] = field(default=())
    episode_metrics: Mapping[str, tuple[str, NestedKey]] = field(default_factory=dict)

    def is_installed(self) -> bool:
        return all(importlib.util.find_spec(m) is not None for m in self.requires)

    def check_installed(self) -> None:
        """Raise :class:`SimulatorNotInstalledError` with the install hint when a module is missing."""
        missing = [m for m in self.requires if importlib.util.find_spec(m) is None]
        if missing:
            raise SimulatorNotInstalledError(
                f"simulator {self.name!r} needs {', '.join(missing)}, which is not installed: "
                f"{self.install_hint}"
            )

    def make(self, task: TaskConfig, num_envs: int, device: torch.device, **options: Any) -> EnvBase:
        self.check_installed()
        if task.obs_mode not in self.obs_modes:
            raise ValueError(
                f"task {task.name!r}: simulator {self.name!r} supports obs_mode in {list(self.obs_modes)}, "
                f"got {task.obs_mode!r}"
            )
        return self.factory(task, num_envs, device, **options)


_REGISTRY: dict[str, SimulatorSpec] = {}


def register_simulator(spec: SimulatorSpec, *, replace: bool = False) -> SimulatorSpec:
    """Add a simulator. A second registration under the same name is an error unless ``replace``."""
    if spec.name in _REGISTRY and not replace and _REGISTRY[spec.name] is not spec:
        raise ValueError(f"a simulator named {spec.name!r} is already registered ({_REGISTRY[spec.name]})")
    _REGISTRY[spec.name] = spec
    return spec


def unregister_simulator(name: str) -> None:
    """Remove a simulator (for test doubles)."""
    _REGISTRY.pop(name, None)


def _load_builtins() -> None:
    for name in BUILTIN_SIMULATORS:
        if name not in _REGISTRY and importlib.util.find_spec(f"l1flow_rl.envs.{name}") is not None:
            importlib.import_module(f"l1flow_rl.envs.{name}")  # registers itself; imports no simulator


def registered_simulators() -> dict[str, SimulatorSpec]:
    """Every registered simulator by name (the built-in packages are imported on first use)."""
    _load_builtins()
    return dict(_REGISTRY)


def get_simulator(name: str) -> SimulatorSpec:
    """The spec registered under ``name``; an unknown name lists the known ones."""
    if name not in _REGISTRY:
        _load_builtins()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(
            f"unknown simulator {name!r}; registered simulators: {sorted(_REGISTRY)} "
            "(a new one registers itself with l1flow_rl.envs.register_simulator)"
        ) from None
