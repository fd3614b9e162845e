"""The field reference of ``docs/cli.md``: every numeric and path field with what it accepts, made
from the declarations beside the fields (:mod:`l1flow_rl.config.ranges`,
:mod:`l1flow_rl.config.path_fields`), so the page cannot drift from the check.

    python -m l1flow_rl.commands.field_reference           # rewrite the section between the markers
    python -m l1flow_rl.commands.field_reference --check   # exit 1 when the page is out of date

Every composed fine-tuning preset is walked, so each algorithm's own settings block is listed too.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from l1flow_rl.commands.cli import COMMANDS, compose_config
from l1flow_rl.config.app import AppConfig
from l1flow_rl.config.path_fields import PATH_KEY
from l1flow_rl.config.paths import CONFIG_DIR
from l1flow_rl.config.ranges import field_range, is_numeric, walk_fields
from l1flow_rl.finetune.registry import builtin_algorithm_names, get_algorithm

__all__ = [
    "BEGIN",
    "END",
    "composed_configs",
    "field_rows",
    "reference_markdown",
    "schema_fields",
    "update_page",
]

BEGIN = "<!-- fields:begin (python -m l1flow_rl.commands.field_reference) -->"
END = "<!-- fields:end -->"
PAGE = Path(__file__).resolve().parents[2] / "docs" / "cli.md"  # a source checkout's


def composed_configs() -> Iterator[tuple[str, DictConfig]]:
    """``(command, composed config)`` for every command, and for ``finetune`` every preset of
    ``configs/finetune/`` (each algorithm's own block)."""
    for command in COMMANDS:
        if command != "finetune":
            yield command, compose_config([], command=command)
    yield from _finetune_presets()


def _finetune_presets() -> Iterator[tuple[str, DictConfig]]:
    for preset in sorted(p.stem for p in (CONFIG_DIR / "finetune").glob("*.yaml")):
        yield "finetune", compose_config([f"finetune={preset}"], command="finetune")


def schema_fields(cfg: DictConfig) -> Iterator[tuple[str, dataclasses.Field, Any, Any]]:
    """Every leaf field ``cfg`` holds, as :func:`~l1flow_rl.config.ranges.walk_fields` yields them:
    the app's schema, then the chosen fine-tuning algorithm's settings block (``finetune.<name>``,
    whose schema the algorithm names)."""
    yield from walk_fields(cfg, AppConfig)
    name = OmegaConf.select(cfg, "finetune.algorithm", default=None)
    if name in builtin_algorithm_names() and OmegaConf.select(cfg, f"finetune.{name}") is not None:
        settings = get_algorithm(name).settings  # the block holds the preset's keys; the rest default
        block = OmegaConf.merge(OmegaConf.structured(settings), cfg.finetune[name])
        yield from walk_fields(block, settings, f"finetune.{name}")


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return "(required)"


def field_rows(configs: list[DictConfig]) -> list[tuple[str, str, str]]:
    """``(key, schema default, what it accepts)`` for every numeric or path field the configs hold,
    in schema order, each key once."""
    rows: dict[str, tuple[str, str, str]] = {}
    for cfg in configs:
        for key, f, hint, _ in schema_fields(cfg):
            if key in rows:
                continue
            rng, rule = field_range(f), f.metadata.get(PATH_KEY)
            if rule is not None:
                allowed = rule.describe()
            elif rng is not None:
                allowed = rng.describe()
            elif is_numeric(hint):
                allowed = "(no declared range)"
            else:
                continue
            default = _default(f)
            rows[key] = (key, "null" if default is None else str(default), allowed)
    return list(rows.values())


def reference_markdown(configs: list[DictConfig] | None = None) -> str:
    """The section between the markers: a table of :func:`field_rows`."""
    if configs is None:  # the schema walk differs by preset only (each algorithm's block)
        configs = [cfg for _, cfg in _finetune_presets()]
    lines = [
        "Every numeric and path field, and what it accepts; a value outside is refused when the config is",
        "composed, in one line naming the key. Generated from the declarations beside the fields",
        "(`bounded(...)`, `path_field(...)` in `l1flow_rl/config/`).",
        "",
        "| key | default | accepts |",
        "|---|---|---|",
    ]
    lines += [f"| `{k}` | `{d}` | {_cell(a)} |" for k, d, a in field_rows(configs)]
    return "\n".join(lines)


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def update_page(text: str, section: str) -> str:
    """``text`` with the part between :data:`BEGIN` and :data:`END` replaced by ``section``."""
    if BEGIN not in text or END not in text:
        raise ValueError(f"the page lacks the markers {BEGIN!r} and {END!r}")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{BEGIN}\n{section}\n{END}{tail}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when docs/cli.md is out of date")
    args = parser.parse_args(argv)
    text = PAGE.read_text()
    new = update_page(text, reference_markdown())
    if args.check:
        if new != text:
            print(f"{PAGE} is out of date: python -m l1flow_rl.commands.field_reference", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
