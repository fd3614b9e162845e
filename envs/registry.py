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
``"reward"``                     float32 [N, 1] (step outputs only)
``"done"``/``"terminated"``/     bool [N, 1]; ``truncated`` at the task's ``max_episode_steps``;
``"truncated"``                  with ``ignore_terminations=True`` nothing but the time limit ends
                                 an episode (ManiSkill's evaluation setting)
``"success"``                    bool [N, 1], the simulator's own success signal (the evaluator's
                                 ``success_once``/``success_at_end`` read it)
``"sim_error"`` (optional)       bool [N, 1], True when a simulator error ended the episode
================================ ====================================================================

Resets are per env and seeded: ``reset(td)`` with ``td["_reset"]`` bool [N, 1] resets only the
marked envs and ``seed=[s, ...]`` gives one seed per env being reset, in env order (a worker env
made of TorchRL's batched envs takes ``list_of_kwargs=[{"seed": s}, ...]`` instead); the same seed
starts the same episode. Envs not reset keep their state and observation. ``render_frames()``
(uint8 [N, H, W, 3]) works when made with ``render=True``, and ``sim_error_message()`` when the env
reports ``"sim_error"``. Extra per-step entries (PushT's ``"coverage"``, ...) are allowed and can
feed ``episode_metrics``. :func:`l1flow_rl.envs.per_env.seeded_reset` and the evaluator use exactly
this. The task's ``env`` block (``task.env``) reaches the factory inside ``task``; the factory reads
it (keys checked against ``SimulatorSpec.env_keys`` where the simulator lists them).
:func:`l1flow_rl.envs.contract.check_env_contract` checks an env against all of this; a simulator
that runs worker processes calls :func:`l1flow_rl.envs.workers.check_main_guard` before starting
them. ``tests/doubles/point_mass`` is a complete, small example of a simulator package.
"""

from __future__ import annotations

import importlib
import importlib.util
import pkgutil
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tensordict.utils import NestedKey

if TYPE_CHECKING:  # pragma: no cover
    import torch
    from torchrl.envs import EnvBase

    from l1flow_rl.config import TaskConfig

__all__ = [
    "SimulatorNotInstalledError",
    "SimulatorSpec",
    "builtin_simulator_packages",
    "check_task_simulator",
    "get_simulator",
    "register_simulator",
    "registered_simulators",
    "unregister_simulator",
]


def builtin_simulator_packages() -> list[str]:
    """The packages under ``l1flow_rl.envs`` (``maniskill``, ``robosuite``, ...): each registers a
    simulator when imported. Found on disk, so that a new simulator package needs no list entry
    here; a package elsewhere registers itself on import (``register_simulator`` is public)."""
    return sorted(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)]) if m.ispkg)


class SimulatorNotInstalledError(ImportError):
    """The simulator a task needs is not importable; the message says how to install it."""


#: How ``episode_metrics`` reduce a per-step entry over an episode's steps.
EPISODE_REDUCTIONS = ("max", "sum", "last", "any")

#: Output entries every simulator's env writes (the module docstring's table).
REQUIRED_ENTRIES: tuple[NestedKey, ...] = ("observation", "success", "done", "terminated", "truncated")


@dataclass(frozen=True)
class SimulatorSpec:
    """How to make and read one simulator's TorchRL env.

    Args:
        name: the value of ``TaskConfig.simulator`` that selects it.
        factory: ``(task, num_envs, device, *, ignore_terminations, render, camera, **options) ->
            EnvBase`` of batch ``[num_envs]`` (see the module docstring for the outputs);
            ``options`` are the simulator's own keyword arguments given to ``make_env`` (named in
            ``options``). The task's ``env`` block arrives inside ``task`` (``task.env``), for the
            factory to read.
        observation_entries: ``task -> {entry: frame_dims}``, the observation entries of one step
            and the number of dims of one frame (1 for a vector, 3 for an image [3, H, W]), so the
            history transforms know where to stack To frames. The entry is ``"observation"`` for
            a flat state or ``("observation", name)`` for the entries of a TensorDict observation.
        install_hint: what to run when the simulator is missing.
        requires: importable module names the simulator needs (checked by :meth:`check_installed`
            without importing them, before anything is built).
        obs_modes: the ``TaskConfig.obs_mode`` values it supports.
        options: the simulator's own ``make_env`` keyword arguments (anything else that is not a
            ``TaskConfig`` field is refused by ``make_env``, naming it).
        env_keys: the keys the task's ``env`` block may hold, checked at config time and by
            ``make_env``; ``None`` (ManiSkill, robosuite) passes the block on to the simulator's
            own constructor (``gym.make``, ``robosuite.make``), which names a key it does not take.
        prepare_dataset: ``(task, path, data_dir) -> path``: makes a demonstration file usable by
            the task before it is read, e.g. robosuite's: a robomimic file without the observations
            the task needs gets a copy under ``data_dir`` with them regenerated from its states.
            None: files are used as they are.
        reader_options: ``task -> options`` for :func:`l1flow_rl.data.load_episodes` that select the
            task's observation from a file (robosuite: ``state_keys`` and cameras). None: none.
        episode_metrics: extra per-episode metrics the evaluator reports (mean and 95 % interval
            over episodes): ``name -> (reduction, step entry)``, reduction one of
            :data:`EPISODE_REDUCTIONS` over the episode's steps; e.g. PushT's Diffusion Policy
            score ``{"score": ("max", "reward")}``.

    Example:
        >>> spec = SimulatorSpec("demo", factory=lambda *a, **k: None,
        ...                      observation_entries=lambda task: {"observation": 1},
        ...                      install_hint="pip install demo-sim", requires=("no_such_module_xyz",))
        >>> spec.is_installed()
        False
    """

    name: str
    factory: Callable[..., EnvBase]
    observation_entries: Callable[[TaskConfig], Mapping[NestedKey, int]]
    install_hint: str
    requires: tuple[str, ...] = ()
    obs_modes: tuple[str, ...] = ("state",)
    options: tuple[str, ...] = field(default=())
    env_keys: tuple[str, ...] | None = None
    prepare_dataset: Callable[[TaskConfig, Path, Path], Path] | None = None
    reader_options: Callable[[TaskConfig], Mapping[str, Any]] | None = None
    episode_metrics: Mapping[str, tuple[str, NestedKey]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.name or not isinstance(self.name, str):
            raise ValueError(f"a simulator needs a non-empty name, got {self.name!r}")
        if not self.obs_modes:
            raise ValueError(f"simulator {self.name!r}: obs_modes is empty")
        for metric, value in self.episode_metrics.items():
            if not (isinstance(value, tuple) and len(value) == 2 and value[0] in EPISODE_REDUCTIONS):
                raise ValueError(
                    f"simulator {self.name!r}: episode_metrics[{metric!r}] must be (reduction, step entry) "
                    f"with reduction in {EPISODE_REDUCTIONS}, got {value!r}"
                )

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

    def task_problems(self, task: TaskConfig) -> list[str]:
        """What is wrong with ``task`` for this simulator, checked without importing or building
        anything (``obs_mode``, the ``env`` block's keys): one line per problem, naming the field."""
        problems = []
        if task.obs_mode not in self.obs_modes:
            problems.append(
                f"task.obs_mode={task.obs_mode!r}: simulator {self.name!r} supports {list(self.obs_modes)}"
            )
        if self.env_keys is not None:
            unknown = sorted(set(task.env or {}) - set(self.env_keys))
            if unknown:
                problems.append(
                    f"task.env: simulator {self.name!r} takes no key(s) {unknown}; "
                    f"it takes {list(self.env_keys)}"
                )
        return problems

    def check_task(self, task: TaskConfig) -> None:
        """Raise before anything is built: :class:`SimulatorNotInstalledError` (with the install
        hint) when the simulator is missing, ``ValueError`` naming each of :meth:`task_problems`."""
        self.check_installed()
        problems = self.task_problems(task)
        if problems:
            raise ValueError(f"task {task.name!r}: " + "; ".join(problems))

    def make(self, task: TaskConfig, num_envs: int, device: torch.device, **options: Any) -> EnvBase:
        """The factory's env, after :meth:`check_task`; its batch size and output entries are
        checked against the contract, so that a new simulator's mistake is named here rather than
        deep inside the trainer or the evaluator."""
        self.check_task(task)
        env = self.factory(task, num_envs, device, **options)
        try:
            self._check_env(env, task, num_envs)
        except Exception:
            env.close()
            raise
        return env

    def _check_env(self, env: EnvBase, task: TaskConfig, num_envs: int) -> None:
        where = f"simulator {self.name!r}, task {task.name!r}: the factory's env"
        if tuple(env.batch_size) != (num_envs,):
            raise ValueError(f"{where} has batch size {tuple(env.batch_size)}, expected ({num_envs},)")
        outputs = set(env.full_observation_spec.keys(True)) | set(env.full_done_spec.keys(True))
        missing = [key for key in REQUIRED_ENTRIES if key not in outputs]
        if missing:
            raise ValueError(f"{where} lacks {missing} in its specs (has {sorted(map(str, outputs))})")
        for entry, frame_dims in self.observation_entries(task).items():
            if entry not in outputs:
                raise ValueError(
                    f"{where} has no observation entry {entry!r} (has {sorted(map(str, outputs))})"
                )
            shape = env.full_observation_spec[entry].shape
            if len(shape) != 1 + int(frame_dims):
                raise ValueError(
                    f"{where}: {entry!r} has shape {tuple(shape)}; observation_entries says a frame has "
                    f"{frame_dims} dim(s) after the batch dim"
                )


_REGISTRY: dict[str, SimulatorSpec] = {}


def register_simulator(spec: SimulatorSpec, *, replace: bool = False) -> SimulatorSpec:
    """Add a simulator. A second registration under the same name is an error unless ``replace``."""
    if spec.name in _REGISTRY and not replace and _REGISTRY[spec.name] is not spec:
        factory = _REGISTRY[spec.name].factory
        raise ValueError(
            f"a simulator named {spec.name!r} is already registered (factory "
            f"{factory.__module__}.{getattr(factory, '__qualname__', factory)}); pick another name, or "
            "pass replace=True to replace it"
        )
    _REGISTRY[spec.name] = spec
    return spec


def check_task_simulator(task: TaskConfig, simulator: str, env: object) -> None:
    """Raise a ValueError naming the task unless it runs on ``simulator``; ``env`` is the env being
    built on it (its class names the env in the message)."""
    if task.simulator != simulator:
        raise ValueError(
            f"task {task.name!r} has simulator={task.simulator!r}; {type(env).__name__} needs {simulator!r}"
        )


def unregister_simulator(name: str) -> None:
    """Remove a simulator (for test doubles)."""
    _REGISTRY.pop(name, None)


def _load_builtins(first: str | None = None) -> None:
    """Import the built-in simulator packages not imported yet (``first`` before the others)."""
    names = builtin_simulator_packages()
    if first in names:
        names.insert(0, names.pop(names.index(first)))
    for name in names:
        module = f"l1flow_rl.envs.{name}"
        if module not in sys.modules:
            importlib.import_module(module)  # registers itself; imports no simulator
        if name == first and first in _REGISTRY:
            return


def registered_simulators() -> dict[str, SimulatorSpec]:
    """Every registered simulator by name (the built-in packages are imported on first use)."""
    _load_builtins()
    return dict(_REGISTRY)


def get_simulator(name: str) -> SimulatorSpec:
    """The spec registered under ``name``; an unknown name lists the known ones."""
    if name not in _REGISTRY:
        _load_builtins(first=name)
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(
            f"unknown simulator {name!r}; registered simulators: {sorted(_REGISTRY)} "
            "(a new one registers itself with l1flow_rl.envs.register_simulator)"
        ) from None
