"""``l1flow-rl``: one entry point, one hydra application per sub-command.

    l1flow-rl train task=maniskill_pushcube policy=l1flow train.steps=3000
    l1flow-rl train -m seed=0,1,2 policy=l1flow,ddpm     # a sweep: 6 runs, one after another
    l1flow-rl train --cfg job                            # print the composed config and exit
    l1flow-rl train --help                               # config groups, their options, the choices

Every run gets its own directory (``run_dir``; by default ``hydra.run.dir`` of ``configs/config.yaml``,
``runs/<task>_<policy>/<date>_<time>``) holding hydra's record of it (``.hydra/config.yaml``,
``overrides.yaml``, ``hydra.yaml``) and the command's log. A sweep (``-m``) runs its jobs in
``hydra.sweep.dir`` (``runs/multirun/<date>_<time>``, or ``run_dir`` when given), one
``<num>_<task>_<policy>_seed<seed>`` folder per job. Before any work, every job's config is composed and
validated (:mod:`l1flow_rl.config.validate`); a bad key or value exits with code 2, naming it.

A benchmark grid is a config of the ``grid`` group (``configs/grid/``): its budgets, its sweep
(``hydra.sweeper.params``), its folder (``hydra.sweep.dir``, ``hydra.sweep.subdir``, which the defaults
above do not replace) and ``resume: auto``, run with any hydra launcher::

    l1flow-rl train -m +grid=success_maniskill                                 # one job at a time
    l1flow-rl train -m +grid=success_maniskill hydra/launcher=joblib hydra.launcher.n_jobs=2
    l1flow-rl eval -m +grid=success_maniskill +rescore=ddim16       # re-score (configs/rescore/)

Relaunched, it skips finished jobs and resumes interrupted ones (``resume=auto``). A job in another
process (joblib, submitit, ray) first imports the modules that registered a simulator, an expert or
a loss in the launching process, so a user's plug-ins work there too.

Errors a user can fix (:class:`~l1flow_rl.errors.UserInputError`: a missing or corrupt data file or
checkpoint, a busy run directory, a run that diverged) print one line,
``l1flow-rl <command>: <what is wrong and what to do>``, and exit with code 2; other exceptions are
bugs and keep their traceback. ``--debug`` (or ``HYDRA_FULL_ERROR=1``) shows the traceback of every
error. A run stopped by SIGTERM or SIGUSR1 checkpoints, prints the command that resumes it and exits
with 128 + the signal's number.

The commands run through hydra's own ``Hydra`` object, as ``@hydra.main`` does, but without its
error reporter, which turns every exception into exit code 1: here exceptions keep their type and
a command's return value is the exit code.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import shlex
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra._internal.hydra import Hydra
from hydra._internal.utils import create_config_search_path, get_args_parser
from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException

from l1flow_rl.config import CONFIG_DIR, AppConfig
from l1flow_rl.config.network import check_moved_keys
from l1flow_rl.config.overrides import open_dict_overrides, user_overrides
from l1flow_rl.config.validate import ConfigValidationError, validate_config
from l1flow_rl.envs.registry import registered_simulators
from l1flow_rl.envs.workers import standard_start_method
from l1flow_rl.errors import RunPreempted, UserInputError
from l1flow_rl.experts.registry import registered_experts
from l1flow_rl.objectives.registry import LOSSES
from l1flow_rl.workspace.run_lock import hold_run_dir

__all__ = ["COMMANDS", "RUN_DIRS", "compose_config", "main"]

#: sub-command -> (module, function taking the composed DictConfig, one-line help)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "train": (
        "l1flow_rl.workspace.train",
        "run_train",
        "generate missing demos, train, evaluate, checkpoint",
    ),
    "eval": ("l1flow_rl.commands.eval", "run_eval", "evaluate a checkpoint: eval.json (+ video on request)"),
    "demos": (
        "l1flow_rl.commands.demos",
        "run_demos",
        "make demonstrations with the task's expert into data_dir",
    ),
    "toy": (
        "l1flow_rl.commands.toy",
        "run_toy",
        "the multi-modality demonstration (paper Fig. 2): toy.png, toy.json",
    ),
    "export": (
        "l1flow_rl.commands.export",
        "run_export",
        "a checkpoint as a pretrained folder (config.json, model.safetensors; program=true: policy.pt2)",
    ),
    "finetune": (
        "l1flow_rl.finetune.loop",
        "run_finetune",
        "flow Q-learning on a BC checkpoint, offline then online: eval.json, checkpoints",
    ),
}

_STAMP = "${now:%Y-%m-%d_%H-%M-%S}"
#: where the sub-commands that do not train a task's policy put their runs: BASE/<date>_<time>, and a
#: sweep's jobs in BASE/multirun_<date>_<time>/<num>; the others use configs/config.yaml's hydra block
RUN_DIRS: dict[str, str] = {
    "eval": "runs/eval",
    "demos": "runs/demos",
    "toy": "runs/toy",
    "finetune": "runs/finetune",
    "export": "runs/export",
}

_CONFIG_NAME = "config"
_INVALID = (HydraException, OmegaConfBaseException, ValueError)


def _store_schema() -> None:
    schema = OmegaConf.structured(AppConfig)
    # ``finetune`` holds the chosen algorithm's own block, finetune.<name>, which the schema cannot name
    # (an algorithm is a folder, or a user's module): the block may be added, and the validator checks
    # it against that algorithm's settings (l1flow_rl.finetune.registry); the common fields stay typed
    OmegaConf.set_struct(schema.finetune, False)
    ConfigStore.instance().store(name="base_config", node=schema)


def _create_hydra(command: str, config_dir: str | None = None) -> Any:
    """hydra's application object for ``command``, searching ``configs/`` (and ``config_dir``)."""
    _store_schema()
    search_path = create_config_search_path(str(CONFIG_DIR))
    if config_dir is not None:
        if not Path(config_dir).is_dir():
            raise ValueError(f"--config-dir {config_dir!r} is not a directory")
        search_path.prepend(provider="command-line", path=f"file://{os.path.abspath(config_dir)}")
    GlobalHydra.instance().clear()
    return Hydra.create_main_hydra2(task_name=command, config_search_path=search_path)


def _compose(hydra: Any, overrides: Sequence[str], mode: RunMode = RunMode.RUN) -> DictConfig:
    """The full config (with hydra's node) of one run of ``overrides`` (``mode`` MULTIRUN: of the
    sweep, its sweep values left out)."""
    return hydra.compose_config(
        config_name=_CONFIG_NAME,
        overrides=list(overrides),
        run_mode=mode,
        with_log_configuration=False,
    )


def _app_config(full: DictConfig) -> DictConfig:
    """The composed config without hydra's node; ``run_dir`` defaults to ``hydra.run.dir``."""
    cfg = full.copy()
    with open_dict(cfg):
        if cfg.get("run_dir") is None and "hydra" in cfg:
            cfg.run_dir = str(cfg.hydra.run.dir)
        cfg.pop("hydra", None)
    OmegaConf.resolve(cfg)
    return cfg


def _configured_sweep(hydra: Any, overrides: Sequence[str]) -> set[str]:
    """The ``hydra.sweep`` fields (``dir``, ``subdir``) that a config the command line adds (a
    grid) sets to other than ``configs/config.yaml``'s: the command's default folder does not
    replace them."""

    def sweep(given: Sequence[str]) -> dict[str, Any]:
        return OmegaConf.to_container(_compose(hydra, given, RunMode.MULTIRUN).hydra.sweep, resolve=False)

    default, composed = sweep([]), sweep(overrides)
    return {key for key in ("dir", "subdir") if composed.get(key) != default.get(key)}


def _run_dir_overrides(
    command: str, overrides: Sequence[str], multirun: bool, configured: set[str] = frozenset()
) -> list[str]:
    """hydra overrides that put the run where ``run_dir`` says, or in the command's default place
    (a sweep: unless ``configured`` names the field, set by a grid's config)."""
    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    given = [o.split("=", 1)[1] for o in overrides if o.lstrip("+").startswith("run_dir=")]
    if any(o.startswith(f"{key}=") for o in overrides):
        return []
    extra = []
    if given and given[-1] not in ("null", "None", ""):
        extra.append(f"{key}={given[-1]}")
    elif command in RUN_DIRS and not (multirun and "dir" in configured):
        extra.append(f"{key}={RUN_DIRS[command]}/{'multirun_' if multirun else ''}{_STAMP}")
    if multirun and command in RUN_DIRS and "subdir" not in configured:
        extra.append("hydra.sweep.subdir=${hydra.job.num}")
    return extra


def compose_config(
    overrides: Sequence[str] = (),
    command: str = "train",
    config_dir: str | None = None,
    paths: bool = False,
) -> DictConfig:
    """The config ``l1flow-rl COMMAND OVERRIDES`` would run with, validated for ``command``.

    Raises hydra's or OmegaConf's error for a bad key or type, and
    :class:`~l1flow_rl.config.validate.ConfigValidationError` for values that cannot work (with
    ``paths``, as the command does, also for path fields that name nothing usable: a checkpoint that
    does not exist, a run directory that cannot be made). ``run_dir`` is filled with the run directory
    the command would use.
    """
    check_moved_keys(overrides)
    overrides = [*open_dict_overrides(overrides), *_run_dir_overrides(command, overrides, multirun=False)]
    hydra = _create_hydra(command, config_dir)
    try:
        full = _compose(hydra, overrides)
    finally:
        GlobalHydra.instance().clear()
    cfg = _app_config(full)
    validate_config(cfg, command, paths=paths)
    return cfg


def _sweep_jobs(hydra: Any, overrides: Sequence[str]) -> list[list[str]]:
    """The override list of every job of a sweep, as hydra's basic sweeper expands it: the config's
    ``hydra.sweeper.params`` (a grid's), then the command line's, which wins for a key in both."""
    params = _compose(hydra, overrides, RunMode.MULTIRUN).hydra.sweeper.get("params") or {}
    given = [*(f"{k}={v}" for k, v in params.items()), *overrides]
    parsed = OverridesParser.create().parse_overrides(given)
    return [job for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


_debug_flag = False  # --debug of the running command


def _debug() -> bool:
    return _debug_flag or os.environ.get("HYDRA_FULL_ERROR") == "1"


def _user_error(command: str, err: UserInputError) -> int:
    print(f"l1flow-rl {command}: {err}", file=sys.stderr)
    return 2


def _resume_command(command: str, overrides: Sequence[str], run_dir: Path) -> str:
    """The command line that continues a stopped run: its overrides, resume=true, its run_dir."""
    kept = [o for o in overrides if o.lstrip("+").split("=", 1)[0] not in ("run_dir", "resume")]
    words = ["l1flow-rl", command, *kept, "resume=true", f"run_dir={run_dir}"]
    return " ".join(shlex.quote(w) for w in words)


def _plugin_modules() -> list[str]:
    """The modules outside the library whose import registered a simulator, an expert or a loss in
    this process (a user's package, a test double): a job that a launcher runs in another process
    imports them again first, so that it sees the same registries. ``__main__`` cannot be imported
    again: a script that registers plug-ins at its top level works with the in-process launcher only."""
    found = [spec.factory for spec in registered_simulators().values()]
    found += [spec.make for spec in registered_experts().values()]
    found += list(LOSSES.values())
    modules = {getattr(obj, "__module__", None) for obj in found if callable(obj)}
    return sorted(m for m in modules if m and m != "__main__" and m.split(".")[0] != "l1flow_rl")


class _Job:
    """The task function hydra runs: ``run_dir`` becomes the job's output directory; a user's
    error is one line and exit code 2 (a sweep goes on with its next job).

    Picklable by reference, for launchers that run jobs in other processes: there it imports the
    launching process's plug-in modules (:func:`_plugin_modules`) and leaves a start method
    multiprocessing does not know (joblib's ``loky``), which the simulators' worker processes could
    not start under (:func:`~l1flow_rl.envs.workers.standard_start_method`)."""

    def __init__(self, command: str, debug: bool = False) -> None:
        self.command, self.debug = command, debug
        self.plugins = _plugin_modules()
        self.__name__ = self.__qualname__ = f"l1flow_rl_{command}"

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        for module in self.plugins:
            importlib.import_module(module)

    def __call__(self, cfg: DictConfig) -> int:
        global _debug_flag
        _debug_flag = _debug_flag or self.debug  # --debug reaches jobs in other processes too
        standard_start_method()
        module, func, _ = COMMANDS[self.command]
        out = Path(HydraConfig.get().runtime.output_dir)
        try:
            shown = str(out.relative_to(Path.cwd()))
        except ValueError:
            shown = str(out)
        with open_dict(cfg):
            cfg.run_dir = shown
        OmegaConf.resolve(cfg)
        try:
            return int(getattr(importlib.import_module(module), func)(cfg) or 0)
        except UserInputError as err:
            if _debug():
                raise
            return _user_error(self.command, err)
        except RunPreempted as stop:  # the exact command that resumes this job, sweep or not
            stop.resume_command = _resume_command(self.command, user_overrides(), stop.run_dir)
            raise


def _groups_help(hydra: Any, overrides: Sequence[str]) -> list[str]:
    """One line per config group: its options, and the one this command line picks."""
    cfg = _compose(hydra, overrides)
    choices = cfg.hydra.runtime.choices
    lines = []
    for group in sorted(g for g in hydra.list_all_config_groups() if not g.startswith("hydra")):
        options = sorted(hydra.config_loader.get_group_options(group))
        text = f"{', '.join(options)}   (now: {choices.get(group)})"
        lines.append(textwrap.fill(text, 104, initial_indent=f"  {group:<8} ", subsequent_indent=" " * 11))
    return lines


def _usage(command: str | None = None, hydra: Any = None, overrides: Sequence[str] = ()) -> str:
    head = f"l1flow-rl {command}: {COMMANDS[command][2]}\n\n" if command else ""
    lines = [
        f"{head}usage: l1flow-rl COMMAND [key=value ...] [-m] [--cfg job|hydra|all [--resolve]] [--help]",
        "",
        "commands:",
    ]
    lines += [f"  {name:<8} {help_}" for name, (_, _, help_) in COMMANDS.items()]
    lines += [
        "",
        "Overrides use hydra syntax, e.g. task=maniskill_pickcube policy=ddim train.steps=500 run_dir=runs/x",
        "  -m / --multirun   a sweep, one run per combination: -m seed=0,1,2 policy=l1flow,ddpm",
        "  --cfg job         print the composed config and exit",
        "  --config-dir DIR  also search DIR for configs (your own task/*.yaml, policy/*.yaml, ...)",
        "  --debug           show the traceback of every error (also: HYDRA_FULL_ERROR=1)",
        "",
        f"config groups (files under {CONFIG_DIR}; pick one with group=option):",
    ]
    if hydra is not None:
        lines += _groups_help(hydra, overrides)
    lines += [
        "",
        "Runs land in runs/<task>_<policy>/<date>_<time>/ (or run_dir=DIR), with hydra's record in .hydra/;",
        "a sweep's jobs in runs/multirun/<date>_<time>/<num>_<task>_<policy>_seed<seed>/.",
    ]
    return "\n".join(lines)


def _one_line(err: BaseException) -> str:
    """hydra's and OmegaConf's message on one line: its sentences, a list after a colon joined by
    commas, then the key it names; their lines of context (types, search path) are dropped."""
    lines = [line.strip() for line in str(err).split("Config search path")[0].splitlines() if line.strip()]
    keys = [line.split(":", 1)[1].strip() for line in lines if line.startswith("full_key:")]
    text, listing = "", False
    for line in lines:
        if line.startswith(("full_key:", "reference_type=", "object_type=")):
            continue
        item = listing and " " not in line
        text += line if not text else (", " if item and not text.endswith(":") else " ") + line
        listing = line.endswith(":") or item
    return f"{text} (key {keys[0]})" if keys and keys[0] and keys[0] not in text else text


def _invalid(command: str, err: Exception) -> int:
    if _debug():
        raise err
    if isinstance(err, ConfigValidationError):  # one line per problem, each naming its key
        for problem in err.problems:
            print(f"l1flow-rl {command}: invalid config: {problem}", file=sys.stderr)
        return 2
    cause = f": {_one_line(err.__cause__)}" if err.__cause__ else ""
    print(f"l1flow-rl {command}: invalid config: {_one_line(err)}{cause}", file=sys.stderr)
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``l1flow-rl COMMAND ...``; returns the exit code (2: bad command line or config)."""
    global _debug_flag
    args = list(sys.argv[1:] if argv is None else argv)
    _debug_flag = "--debug" in args  # tracebacks for every error, as hydra's HYDRA_FULL_ERROR=1
    args = [a for a in args if a != "--debug"]
    if not args or args[0] in ("-h", "--help", "help"):
        hydra = _create_hydra("help")
        try:
            print(_usage(hydra=hydra))
        finally:
            GlobalHydra.instance().clear()
        return 0
    command, rest = args[0], args[1:]
    if command not in COMMANDS:
        print(f"l1flow-rl: unknown command {command!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    parser = get_args_parser()
    parser.prog = f"l1flow-rl {command}"
    try:
        hargs = parser.parse_args(rest)
    except SystemExit as exit_:  # argparse has printed what is wrong
        return int(exit_.code or 0)
    unsupported = [
        flag
        for flag, on in (
            ("--config-name", hargs.config_name),
            ("--config-path", hargs.config_path),
            ("--experimental-rerun", hargs.experimental_rerun),
            ("--shell-completion", hargs.shell_completion),
        )
        if on
    ]
    if unsupported:
        print(f"l1flow-rl {command}: {', '.join(unsupported)} is not supported here", file=sys.stderr)
        return 2
    # policy.sampler_kwargs.steps=16 may add a key the policy file lacks (l1flow_rl.config.overrides)
    overrides = open_dict_overrides(hargs.overrides)
    try:
        hydra = _create_hydra(command, hargs.config_dir)
    except _INVALID as err:
        return _invalid(command, err)
    try:
        if hargs.help or hargs.hydra_help:
            if hargs.hydra_help:
                hydra.hydra_help(config_name=_CONFIG_NAME, args_parser=parser, args=hargs)
            else:
                print(_usage(command, hydra, overrides))
            return 0
        return _run(command, hydra, hargs, overrides)
    except UserInputError as err:  # raised outside a job (the run directory's lock)
        if _debug():
            raise
        return _user_error(command, err)
    except RunPreempted as stop:
        if int(os.environ.get("RANK", "0")) == 0:  # under torchrun, one message for the run
            print(f"l1flow-rl {command}: {stop}", file=sys.stderr)
        return stop.exit_code
    finally:
        GlobalHydra.instance().clear()


def _secondary_rank_overrides(overrides: Sequence[str]) -> list[str]:
    """Under torchrun, only rank 0 keeps hydra's record and log: the others would write the same
    files, or (default run_dir, stamped to the second) make a second, empty run directory."""
    if int(os.environ.get("RANK", "0")) == 0:
        return []
    extra = ["hydra.output_subdir=null", "hydra/job_logging=none", "hydra/hydra_logging=none"]
    if not any(o.lstrip("+").startswith(("run_dir=", "hydra.run.dir=")) for o in overrides):
        extra.append("hydra.run.dir=.")  # unused there: rank 0 writes the run
    return extra


def _run(command: str, hydra: Any, hargs: Any, overrides: list[str]) -> int:
    multirun = bool(hargs.multirun)
    # Compose and validate every job (its paths included) before the first one starts, so that a
    # refused command line leaves no run directory and no lock behind.
    try:
        configured = _configured_sweep(hydra, overrides) if multirun else set()
        overrides = [
            *overrides,
            *_run_dir_overrides(command, overrides, multirun, configured),
            *_secondary_rank_overrides(overrides),
        ]
        check_moved_keys(overrides)  # policy.down_dims=... from before the network group: name the new key
        for job in _sweep_jobs(hydra, overrides) if multirun else [overrides]:
            full = _compose(hydra, job)
            # a grid's paths may name hydra's own fields (checkpoint: ${hydra:sweep.dir}/...)
            HydraConfig.instance().set_config(full)
            try:
                validate_config(_app_config(full), command, paths=True)
            finally:
                HydraConfig.instance().cfg = None
    except _INVALID as err:
        return _invalid(command, err)
    if hargs.cfg or hargs.info:
        if hargs.info:
            hydra.show_info(hargs.info, config_name=_CONFIG_NAME, overrides=overrides)
        else:
            hydra.show_cfg(
                config_name=_CONFIG_NAME,
                overrides=overrides,
                cfg_type=hargs.cfg,
                package=hargs.package,
                resolve=hargs.resolve,
            )
        return 0
    task = _Job(command, _debug_flag)
    if not multirun:
        given = [o.split("=", 1)[1] for o in overrides if o.startswith("hydra.run.dir=")]
        with contextlib.ExitStack() as stack:
            if given and "${" not in given[-1] and int(os.environ.get("RANK", "0")) == 0:
                # Locked before hydra writes its record (.hydra/, the log) into the directory.
                stack.enter_context(hold_run_dir(given[-1]))
            return int(
                hydra.run(config_name=_CONFIG_NAME, task_function=task, overrides=overrides).return_value
            )
    batches = hydra.multirun(
        config_name=_CONFIG_NAME, task_function=task, overrides=[*overrides, "hydra.mode=MULTIRUN"]
    )
    codes = [int(r.return_value) for batch in batches for r in batch]
    return max(codes, default=0)


if __name__ == "__main__":
    sys.exit(main())
