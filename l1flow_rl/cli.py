"""``l1flow-rl``: one entry point, one sub-command per job, hydra overrides for everything else.

l1flow-rl train task=maniskill_pushcube policy=l1flow train.steps=3000
l1flow-rl train --cfg job          # print the composed config and exit
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from l1flow_rl.config import CONFIG_DIR, AppConfig

__all__ = ["COMMANDS", "compose_config", "main"]

#: sub-command -> (module, function taking the composed DictConfig, one-line help)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "train": (
        "l1flow_rl.workspace.train",
        "run_train",
        "generate missing demos, train, evaluate, checkpoint",
    ),
    "eval": ("l1flow_rl.evaluation", "run_eval", "evaluate a checkpoint: eval.json (+ video on request)"),
    "demos": (
        "l1flow_rl.experts.cli",
        "run_demos",
        "make demonstrations with the task's expert into data_dir",
    ),
    "toy": ("l1flow_rl.toy", "run_toy", "the multi-modality demonstration (paper Fig. 2): toy.png, toy.json"),
}

_stored = False


def _store_schema() -> None:
    global _stored
    if not _stored:
        ConfigStore.instance().store(name="base_config", node=AppConfig)
        _stored = True


def compose_config(overrides: Sequence[str] = ()) -> DictConfig:
    """Compose ``configs/config.yaml`` with hydra overrides, validated against :class:`AppConfig`."""
    _store_schema()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=list(overrides))
    OmegaConf.resolve(cfg)
    return cfg


def _usage() -> str:
    lines = ["usage: l1flow-rl COMMAND [key=value ...] [--cfg job]", "", "commands:"]
    lines += [f"  {name:<8} {help_}" for name, (_, _, help_) in COMMANDS.items()]
    lines += [
        "",
        "Overrides use hydra syntax, e.g. task=maniskill_pickcube policy=ddim train.steps=500 run_dir=runs/x",
        f"Config groups: task, policy (files under {CONFIG_DIR}).",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    command, rest = args[0], args[1:]
    if command not in COMMANDS:
        print(f"l1flow-rl: unknown command {command!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    if any(a in ("-h", "--help") for a in rest):
        print(f"l1flow-rl {command}: {COMMANDS[command][2]}\n\n{_usage()}")
        return 0
    print_cfg = False
    overrides = []
    i = 0
    while i < len(rest):
        if rest[i] in ("--cfg=job", "-c=job") or (
            rest[i] in ("--cfg", "-c") and rest[i + 1 : i + 2] == ["job"]
        ):
            print_cfg = True
            i += 1 if "=" in rest[i] else 2
            continue
        overrides.append(rest[i])
        i += 1
    try:
        cfg = compose_config(overrides)
    except (HydraException, OmegaConfBaseException, ValueError) as err:
        cause = f"\n  cause: {err.__cause__}" if err.__cause__ else ""
        print(f"l1flow-rl {command}: invalid config: {err}{cause}", file=sys.stderr)
        return 2
    if print_cfg:
        print(OmegaConf.to_yaml(cfg))
        return 0
    module, func, _ = COMMANDS[command]
    return int(getattr(importlib.import_module(module), func)(cfg) or 0)


if __name__ == "__main__":
    sys.exit(main())
