"""Valid ranges declared where config fields are declared, and the one check that enforces them.

A numeric field of a config dataclass says what it accepts beside its default::

    @dataclass
    class TrainConfig:
        steps: int = bounded(3000, ge=0)
        lr: float = bounded(1e-4, gt=0)
        eval_every: int = bounded(0, ge=0, zero="evaluate only at the end")
        betas: list[float] = bounded(lambda: [0.95, 0.999], ge=0, lt=1, each=True)

:func:`range_problems` walks a composed config against its schema and returns one line per value
outside its range, naming the dotted key, the value and what is allowed; the config validator runs it
at compose time, before any demonstration, network or simulator is built. :func:`declared_ranges`
lists every declared field (the schema sweep test and the generated field reference read it).
Hand-written because neither OmegaConf nor hydra checks numeric bounds, and pydantic would replace
the dataclass schemas that hydra's structured configs need.

Example:
    >>> from dataclasses import dataclass
    >>> from omegaconf import OmegaConf
    >>> @dataclass
    ... class Opt:
    ...     lr: float = bounded(1e-3, gt=0)
    ...     steps: int = bounded(10, ge=0, zero="no training")
    >>> range_problems(OmegaConf.create({"lr": -1.0, "steps": 0}), Opt, prefix="train")
    ['train.lr=-1.0: expected > 0']
"""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

__all__ = [
    "RANGE_KEY",
    "Range",
    "bounded",
    "declared_ranges",
    "field_range",
    "is_numeric",
    "range_problems",
    "walk_fields",
]

#: the dataclass field metadata key that holds a field's :class:`Range`
RANGE_KEY = "l1flow_rl.range"


@dataclass(frozen=True)
class Range:
    """What a numeric field accepts: bounds (any of ``ge``, ``gt``, ``le``, ``lt``), what 0 means where
    0 is a documented special value inside them (``zero``), whether ``None`` is allowed (``optional``),
    and for a list field whether the bounds hold for each element (``each``)."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    zero: str | None = None
    optional: bool = False
    each: bool = False

    def describe(self) -> str:
        """The allowed values in words, e.g. ``>= 1``, ``in [0, 1)``, ``>= 0 (0: only at the end)``."""
        low = (
            f"[{_num(self.ge)}"
            if self.ge is not None
            else f"({_num(self.gt)}"
            if self.gt is not None
            else None
        )
        high = (
            f"{_num(self.le)}]"
            if self.le is not None
            else f"{_num(self.lt)})"
            if self.lt is not None
            else None
        )
        if low and high:
            text = f"in {low}, {high}"
        elif low:
            text = (">= " if low[0] == "[" else "> ") + low[1:]
        elif high:
            text = ("<= " if high[-1] == "]" else "< ") + high[:-1]
        else:
            text = "any number"
        if self.each:
            text = f"each {text}"
        if self.zero:
            text += f" (0: {self.zero})"
        if self.optional:
            text += ", or null"
        return text

    def admits(self, value: Any) -> bool:
        """Whether one number lies in the range (NaN never does; ``None`` only where optional)."""
        if value is None:
            return self.optional
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if isinstance(value, float) and math.isnan(value):
            return False
        return not (
            (self.ge is not None and value < self.ge)
            or (self.gt is not None and value <= self.gt)
            or (self.le is not None and value > self.le)
            or (self.lt is not None and value >= self.lt)
        )

    def outside(self) -> list[float]:
        """Values just outside the range, one per bound (what the schema sweep test tries)."""
        out: list[float] = []
        if self.ge is not None:
            out.append(self.ge - 1 if float(self.ge).is_integer() else self.ge - 1e-3)
        if self.gt is not None:
            out.append(self.gt)
        if self.le is not None:
            out.append(self.le + 1 if float(self.le).is_integer() else self.le + 1e-3)
        if self.lt is not None:
            out.append(self.lt)
        return out


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def bounded(
    default: Any = dataclasses.MISSING,
    *,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    zero: str | None = None,
    optional: bool = False,
    each: bool = False,
) -> Any:
    """A dataclass field with its valid range in its metadata. ``default`` is the value, or a callable
    that makes it (a list default, e.g. ``lambda: [0.95, 0.999]`` with ``each=True``)."""
    meta = {RANGE_KEY: Range(ge=ge, gt=gt, le=le, lt=lt, zero=zero, optional=optional, each=each)}
    if callable(default):
        return dataclasses.field(default_factory=default, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def field_range(f: dataclasses.Field) -> Range | None:
    """The :class:`Range` declared on a dataclass field, or None."""
    return f.metadata.get(RANGE_KEY)


def _resolved_hints(schema: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(schema)
    except Exception:  # a forward reference the module cannot resolve: fall back to raw annotations
        return {f.name: f.type for f in dataclasses.fields(schema)}


def _nested_schema(hint: Any) -> type | None:
    """The dataclass a field's type names (``X`` or ``X | None``), or None."""
    for candidate in (hint, *typing.get_args(hint)):
        if isinstance(candidate, type) and dataclasses.is_dataclass(candidate):
            return candidate
    return None


def declared_ranges(schema: type, prefix: str = "") -> Iterator[tuple[str, Range | None, Any]]:
    """Every field of ``schema`` (nested dataclasses walked) as ``(dotted key, its Range or None, its
    type)``: numeric fields with None have no declared range."""
    hints = _resolved_hints(schema)
    for f in dataclasses.fields(schema):
        key = f"{prefix}.{f.name}" if prefix else f.name
        hint = hints.get(f.name, f.type)
        nested = _nested_schema(hint)
        if nested is not None:
            yield from declared_ranges(nested, key)
            continue
        yield key, field_range(f), hint


def is_numeric(hint: Any) -> bool:
    """Whether a field of type ``hint`` holds numbers (``int``, ``float``, a list of them, or either
    ``| None``; not ``bool``): the fields that must declare a range."""
    if hint in (int, float):
        return True
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    origin = typing.get_origin(hint)
    if origin in (list, tuple):
        return bool(args) and all(a in (int, float) for a in args if a is not Ellipsis)
    if args and origin is not None and len(args) == 1 and len(typing.get_args(hint)) == 2:  # X | None
        return is_numeric(args[0])
    return False


def _plain(node: Any) -> Any:
    if isinstance(node, (DictConfig, ListConfig)):
        return OmegaConf.to_container(node, resolve=True)
    return node


def walk_fields(
    cfg: Any, schema: type, prefix: str = ""
) -> Iterator[tuple[str, dataclasses.Field, Any, Any]]:
    """Every leaf field of ``schema`` that ``cfg`` holds, as ``(dotted key, field, type, value)``,
    nested dataclasses walked (what :func:`range_problems` checks; the schema sweep test and the
    field reference walk the same). A fine-tuning algorithm's own block is walked against its settings
    by :mod:`l1flow_rl.finetune.registry`, which knows the chosen algorithm."""
    if cfg is None or not isinstance(cfg, (DictConfig, dict)):
        return
    hints = _resolved_hints(schema)
    for f in dataclasses.fields(schema):
        key = f"{prefix}.{f.name}" if prefix else f.name
        if f.name not in cfg:
            continue
        value = cfg[f.name]
        nested = _nested_schema(hints.get(f.name, f.type))
        if nested is not None:
            yield from walk_fields(value, nested, key)
        else:
            yield key, f, hints.get(f.name, f.type), value


def range_problems(cfg: Any, schema: type, prefix: str = "") -> list[str]:
    """One line per value of ``cfg`` outside the range its ``schema`` field declares (nested
    dataclasses walked), each ``key=value: expected <range>``. Fields
    absent from ``cfg`` are skipped."""
    problems: list[str] = []
    if isinstance(cfg, DictConfig):  # walked as plain dicts: a tenth of the cost of DictConfig look-ups
        cfg = _plain(cfg)
    for key, f, _, value in walk_fields(cfg, schema, prefix):
        rng = field_range(f)
        if rng is None:
            continue
        value = _plain(value)
        if rng.each and isinstance(value, (list, tuple)):
            bad = [v for v in value if not rng.admits(v)]
            if bad:
                problems.append(f"{key}={value}: expected {rng.describe()}")
        elif not rng.admits(value):
            problems.append(f"{key}={value!r}: expected {rng.describe()}")
    return problems
