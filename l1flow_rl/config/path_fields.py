"""Path fields declared where config fields are declared, and the check that enforces them.

A path field of a config dataclass says what it must name, beside its default::

    @dataclass
    class AppConfig:
        data_dir: str = path_field("data", kind=WRITABLE_DIR, commands=("train", "demos", "finetune"))
        checkpoint: str | None = path_field(None, kind=EXISTING, required=("eval", "export"))

Kinds: :data:`WRITABLE_DIR` (a directory that exists or can be made, and can be written: probed by
making and removing an empty directory in it or in its nearest existing ancestor), :data:`EXISTING`
(a file or directory that exists) and :data:`DATASET` (a demonstration file or folder in a supported
format, told from its content as the data loader tells it). ``commands`` names the sub-commands that
use the field (None: all of them); ``required`` those that cannot run without it. :func:`path_problems`
returns one line per refused value, naming the dotted key, the value and what is wanted; the CLI runs
it with the other config checks before anything is written. :func:`declared_paths` lists every
declared field (the schema sweep test and the generated field reference read it).
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from l1flow_rl.config.ranges import _nested_schema, _resolved_hints

__all__ = [
    "DATASET",
    "EXISTING",
    "PATH_KEY",
    "WRITABLE_DIR",
    "PathRule",
    "declared_paths",
    "path_field",
    "path_problems",
]

#: the dataclass field metadata key that holds a field's :class:`PathRule`
PATH_KEY = "l1flow_rl.path"

WRITABLE_DIR = "writable directory"
EXISTING = "existing file or directory"
DATASET = "demonstration dataset"
_KINDS = (WRITABLE_DIR, EXISTING, DATASET)


@dataclass(frozen=True)
class PathRule:
    """What a path field must name (``kind``), for which commands, and where it may not be null."""

    kind: str
    commands: frozenset[str] | None = None
    required: frozenset[str] = frozenset()

    def describe(self) -> str:
        """The rule in words, e.g. ``a writable directory, existing or creatable; read by demos, train``."""
        text = {
            WRITABLE_DIR: "a writable directory, existing or creatable",
            EXISTING: "an existing file or directory",
            DATASET: "an existing dataset (ManiSkill .h5, robomimic .hdf5, .zarr, LeRobot folder)",
        }[self.kind]
        if self.commands:
            text += f"; read by {', '.join(sorted(self.commands))}"
        if self.required:
            text += f"; required by {', '.join(sorted(self.required))}"
        return text

    def applies_to(self, command: str) -> bool:
        return self.commands is None or command in self.commands or command in self.required

    def problem(
        self, value: Any, command: str, dataset_problem: Callable[[Path], str | None] | None = None
    ) -> str | None:
        """Why ``value`` cannot serve ``command``, or None. ``dataset_problem(path)`` tells a dataset's
        format (the data layer's detection, which the validator passes in); without it a dataset
        only has to exist."""
        if not self.applies_to(command):
            return None
        if value is None or value == "":
            return f"{command} needs it" if command in self.required else None
        path = Path(str(value)).expanduser()
        if self.kind == WRITABLE_DIR:
            return _unwritable(path)
        if not path.exists():
            return "no such file or directory"
        return dataset_problem(path) if self.kind == DATASET and dataset_problem is not None else None


def path_field(
    default: Any = dataclasses.MISSING,
    *,
    kind: str,
    commands: Iterable[str] | None = None,
    required: Iterable[str] = (),
) -> Any:
    """A dataclass field with its :class:`PathRule` in its metadata."""
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {list(_KINDS)}, got {kind!r}")
    rule = PathRule(kind, None if commands is None else frozenset(commands), frozenset(required))
    return dataclasses.field(default=default, metadata={PATH_KEY: rule})


def _unwritable(path: Path) -> str | None:
    """Why no run could write under ``path`` (None: it can). Probed by making and removing an empty
    directory, since ``os.access`` answers yes to root where the file system refuses (``/proc``)."""
    existing = path
    while not existing.exists():
        if existing.parent == existing:
            return "no existing ancestor"
        existing = existing.parent
    if not existing.is_dir():
        where = "it" if existing == path else str(existing)
        return f"{where} is a file, not a directory"
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".l1flow-probe-", dir=existing))
    except OSError as err:
        return f"cannot create or write in {str(existing)!r}: {err.strerror or err}"
    return None


def declared_paths(schema: type, prefix: str = "") -> Iterator[tuple[str, PathRule]]:
    """Every path field of ``schema`` (nested dataclasses walked) as ``(dotted key, its PathRule)``."""
    hints = _resolved_hints(schema)
    for f in dataclasses.fields(schema):
        key = f"{prefix}.{f.name}" if prefix else f.name
        nested = _nested_schema(hints.get(f.name, f.type))
        if nested is not None:
            yield from declared_paths(nested, key)
        elif PATH_KEY in f.metadata:
            yield key, f.metadata[PATH_KEY]


def path_problems(
    cfg: DictConfig,
    schema: type,
    command: str,
    dataset_problem: Callable[[Path], str | None] | None = None,
) -> list[str]:
    """One line per path field of ``cfg`` that cannot serve ``command``: ``key=value: <why not>;
    expected <what>`` (``dataset_problem``: see :meth:`PathRule.problem`)."""
    problems = []
    for key, rule in declared_paths(schema):
        node: Any = cfg
        for part in key.split("."):
            node = node.get(part) if isinstance(node, (DictConfig, dict)) else None
        why = rule.problem(node, command, dataset_problem)
        if why is not None:
            problems.append(f"{key}={node!r}: {why}; expected {rule.describe()}")
    return problems
