"""The fine-tuning algorithms by name: a folder of this package, or a user's module, found by import.

``finetune.algorithm`` names a built-in algorithm (a sub-package of :mod:`l1flow_rl.finetune`:
``qc``, ``fql``, ...) or the import path of a module outside the library (``my_package.my_algorithm``);
either defines ``ALGORITHM``, a :class:`~l1flow_rl.finetune.base.FinetuneAlgorithm`. There is no list
to edit: a new folder with an ``ALGORITHM`` is an algorithm. The config validator asks
:func:`finetune_problems` (the name, the settings block's keys, types and ranges, the algorithm's
data rules) before any work; ``l1flow-rl finetune`` and ``load_actor`` ask :func:`get_algorithm`.

Example:
    >>> from omegaconf import OmegaConf
    >>> from l1flow_rl import L1FlowActor
    >>> from l1flow_rl.config.finetune import FinetuneConfig
    >>> cfg = OmegaConf.structured(FinetuneConfig(algorithm="fql", critic_hidden_dims=[32]))
    >>> flow = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
    >>> loss = get_algorithm("fql").build(flow, cfg)
    >>> type(loss).__name__, type(loss.actor).__name__
    ('FQLLoss', 'OneStepActor')
    >>> print(*settings_problems(get_algorithm("qc"), {"num_samples": 0}))
    finetune.qc.num_samples=0: expected >= 1
"""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from l1flow_rl.config.finetune import FinetuneConfig
from l1flow_rl.config.ranges import range_problems
from l1flow_rl.finetune.base import FinetuneAlgorithm

__all__ = [
    "UnknownAlgorithmError",
    "builtin_algorithm_names",
    "finetune_problems",
    "get_algorithm",
    "settings_problems",
]

_PACKAGE = "l1flow_rl.finetune"


class UnknownAlgorithmError(ValueError):
    """``finetune.algorithm`` names no built-in algorithm and no importable module with an ``ALGORITHM``."""


def builtin_algorithm_names() -> list[str]:
    """The algorithm folders of :mod:`l1flow_rl.finetune` (each sub-package is one)."""
    return sorted(m.name for m in pkgutil.iter_modules([str(Path(__file__).parent)]) if m.ispkg)


def get_algorithm(name: str) -> FinetuneAlgorithm:
    """The ``ALGORITHM`` of the built-in folder ``name``, or of the module at the import path ``name``."""
    builtins = builtin_algorithm_names()
    if "." not in str(name):
        if name not in builtins:
            raise UnknownAlgorithmError(
                f"finetune.algorithm={name!r}: expected one of {builtins}, or the import path of a module "
                "that defines ALGORITHM (my_package.my_algorithm)"
            )
        path = f"{_PACKAGE}.{name}"
    else:
        path = str(name)
    try:
        module = importlib.import_module(path)  # the plug-in lookup: by name, as the simulators'
    except ModuleNotFoundError as err:
        if err.name is None or not path.startswith(err.name):
            raise  # the module exists but one of its own imports is missing: its traceback says which
        raise UnknownAlgorithmError(
            f"finetune.algorithm={name!r}: no module {err.name!r} to import; expected one of {builtins}, or "
            "the import path of a module that defines ALGORITHM (on sys.path)"
        ) from None
    algorithm = getattr(module, "ALGORITHM", None)
    if not isinstance(algorithm, FinetuneAlgorithm):
        raise UnknownAlgorithmError(
            f"finetune.algorithm={name!r}: module {path!r} defines no ALGORITHM (a "
            f"l1flow_rl.finetune.base.FinetuneAlgorithm instance), got {type(algorithm).__name__}"
        )
    if not algorithm.name or algorithm.name in _COMMON_FIELDS:
        raise UnknownAlgorithmError(
            f"finetune.algorithm={name!r}: its ALGORITHM.name={algorithm.name!r} must name its settings "
            f"block finetune.<name>, apart from the common fields {sorted(_COMMON_FIELDS)}"
        )
    return algorithm


_COMMON_FIELDS = frozenset(f.name for f in dataclasses.fields(FinetuneConfig))


def _type_name(hint: Any) -> str:
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


def settings_problems(algorithm: FinetuneAlgorithm, block: Any) -> list[str]:
    """Problems of the block ``finetune.<name>`` against the algorithm's settings dataclass, one line
    each: a key it lacks, a value of the wrong type, a number outside its declared range."""
    prefix = f"finetune.{algorithm.name}"
    if block is None:
        return []
    if not isinstance(block, (dict, DictConfig)):
        return [f"{prefix}={block!r}: expected a block of settings (keys of {algorithm.settings.__name__})"]
    fields = {f.name: f for f in dataclasses.fields(algorithm.settings)}
    problems = []
    schema = OmegaConf.structured(algorithm.settings)
    for key in block:
        if key not in fields:
            problems.append(
                f"{prefix}.{key}: not a setting of {algorithm.name}; its settings: {sorted(fields)}"
            )
            continue
        try:
            OmegaConf.merge(schema, {key: block[key]})
        except OmegaConfBaseException:
            value = (
                OmegaConf.to_container(block, resolve=True)[key]
                if isinstance(block, DictConfig)
                else block[key]
            )
            problems.append(f"{prefix}.{key}={value!r}: expected {_type_name(fields[key].type)}")
    if problems:
        return problems
    return range_problems(OmegaConf.merge(schema, block), algorithm.settings, prefix=prefix)


def _block_problems(ft: DictConfig, algorithm: FinetuneAlgorithm) -> list[str]:
    """Keys of ``finetune`` that are neither common fields nor the chosen algorithm's block: another
    built-in algorithm's block is checked as its own (a command line shared by several algorithms'
    runs sets each one's settings; each run reads its own), anything else is refused."""
    problems = []
    for key in ft:
        if key in _COMMON_FIELDS or key == algorithm.name:
            continue
        if key in builtin_algorithm_names():
            problems += settings_problems(get_algorithm(key), ft[key])
        else:
            problems.append(
                f"finetune.{key}: not a fine-tuning setting; expected one of {sorted(_COMMON_FIELDS)} or "
                f"finetune.{algorithm.name} (the settings of finetune.algorithm={ft.algorithm})"
            )
    return problems


def finetune_problems(cfg: DictConfig, command: str) -> list[str]:
    """The config validator's check of ``finetune``: the algorithm's name, its settings block and the
    other keys of ``finetune``; for ``l1flow-rl finetune``, also the algorithm's data rules (the start
    checkpoint's fit: :func:`l1flow_rl.finetune.start_check.start_problems`)."""
    ft = cfg.get("finetune") if isinstance(cfg, DictConfig) else None
    if ft is None or ft.get("algorithm") is None:
        return []
    try:
        algorithm = get_algorithm(ft.algorithm)
    except UnknownAlgorithmError as err:
        return [str(err)]
    problems = _block_problems(ft, algorithm) + settings_problems(algorithm, ft.get(algorithm.name))
    if command == "finetune":
        problems += algorithm.check(cfg)
    return problems
