"""Success and convergence, side by side (the paper's Table 2 and Figure 4 at this machine's scale),
collected from a success grid's runs.

A grid is a hydra multirun of ``l1flow-rl train`` (``configs/grid/success_*.yaml``: tasks x methods x
seeds with their budgets), run with any launcher; the DDPM networks' DDIM-16 re-scoring, the
ManiSkill protocol and the last weights' test are ``l1flow-rl eval -m`` over its checkpoints
(``configs/rescore/``). Relaunching a stopped grid skips its finished jobs and resumes the others::

    l1flow-rl train -m +grid=success_maniskill          # hydra/launcher=joblib, submitit_slurm, ...
    l1flow-rl eval -m +grid=success_maniskill +rescore=ddim16  # and maniskill_protocol, last_weights
    python -m benchmarks.success.bench_success runs/grid/success_maniskill --plot success.png

This script reads the grid's folder (``hydra.sweep.dir``) and trains nothing. Saved: one
``benchmarks/results/success_<task>.json`` per task of the grid (``--tag T``: ``success_T.json``, or
``success_T_<task>.json`` for several tasks): per method, final success_once with its 95 % Wilson
interval, the protocol's headline metric (PushT: Diffusion Policy's score), mean and spread over seeds,
each run's budget (steps, wall and CPU seconds from its summary.json), the validation curve and
steps to 90 % of its best; each re-scoring ``rescore_<name>`` under the label ``<method>_<name>``.
``args`` holds the grid's setting, read from the runs' configs (``extra``: every setting the runs
share that differs from the task's and method's defaults); ``provenance.runs`` the commits the runs
were measured at, their launchers, their shared resolved config and what the grid swept
(``benchmarks.lib.runs.grid_provenance``). A grid with an unfinished run or re-scoring is refused
(exit 2, listing each) unless ``--partial``.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path
from typing import Any

from hydra.errors import HydraException
from omegaconf import OmegaConf

from benchmarks.lib.common import (
    RESULTS_DIR,
    format_table,
    machine_info,
    parse_args,
    provenance,
    save_results,
)
from benchmarks.lib.figures import plot_success_curves
from benchmarks.lib.runs import (
    Run,
    grid_provenance,
    grid_runs,
    headline_metric,
    read_history,
    run_budget,
    seed_record,
)
from benchmarks.lib.stats import mean_and_spread, steps_to_fraction_of_best
from l1flow_rl.commands.cli import compose_config
from l1flow_rl.config import CONFIG_DIR
from l1flow_rl.workspace.checkpoint import flatten_config

#: the network configs a run may have chosen (``network=<name>``)
NETWORK_CONFIGS = Path(CONFIG_DIR) / "network"

__all__ = ["collect", "finished_enough", "grid_extra", "grid_setting", "main"]

#: fields every grid sets for itself, which ``args`` holds on their own (or which say nothing of
#: what was measured): never listed among the ``extra`` settings
SETTING_FIELDS = (
    "seed",
    "run_dir",
    "data_dir",
    "resume",
    "device",
    "checkpoint",
    "demos.num",
    "train.steps",
    "train.eval_every",
    "train.checkpoint_every",
    "train.log_every",
    "train.logger",
    "eval.episodes",
    "eval.val_episodes",
    "eval.val_sampler",
    "eval.val_sampler_kwargs",
)


@functools.cache  # one composition per (task, method, network), not one per run
def _defaults(task: str, policy: str, network: str | None = None) -> tuple[dict[str, Any], bool]:
    """The flattened default config of ``task=<task> policy=<policy>`` (and ``network=<network>``),
    and whether the task's own fields are in it (a task without a config file, set field by field,
    compares the rest only)."""
    group = [f"network={network}"] if network else []
    # validated as for eval: a distilled method's training defaults lack the teacher its runs named
    try:
        composed = compose_config([f"task={task}", f"policy={policy}", *group], command="eval")
    except HydraException:  # no configs/task/<task>.yaml: the run set the task's fields one by one
        plain = compose_config([f"policy={policy}", *group], command="eval")
        return flatten_config(OmegaConf.to_container(plain)), False
    return flatten_config(OmegaConf.to_container(composed)), True


def grid_extra(runs: list[Run]) -> list[str]:
    """The settings every run shares that differ from its task's and method's defaults, as
    ``key=value`` overrides (``SETTING_FIELDS`` left out): what makes this grid other than the plain
    command, e.g. ``eval.protocol=diffusion_policy`` or ``network=mlp`` (a network config's own
    fields are compared with that config's, so that choosing it reads as one override)."""
    shared: dict[str, Any] | None = None
    for run in runs:
        task, network = run.setting("task.name"), run.setting("network.name")
        policy = run.choice("policy") or run.setting("policy.name")
        defaults, with_task = _defaults(task, policy)
        chosen = network != defaults.get("network.name") and (NETWORK_CONFIGS / f"{network}.yaml").is_file()
        if chosen:
            defaults, with_task = _defaults(task, policy, network)
        diffs = {
            key: value
            for key, value in flatten_config(run.config).items()
            if defaults.get(key) != value
            and not any(key == f or key.startswith(f + ".") for f in SETTING_FIELDS)
            and (with_task or not key.startswith("task."))
        }
        if chosen:
            diffs["network"] = network
        shared = diffs if shared is None else {k: v for k, v in shared.items() if diffs.get(k, object()) == v}
    return [f"{k}={v if isinstance(v, str) else json.dumps(v)}" for k, v in sorted((shared or {}).items())]


def _validation_sampler(runs: list[Run]) -> str | None:
    """The validation curve's sampler where it is not the method's own (e.g. ``ddim16``)."""
    names = set()
    for run in runs:
        sampler = run.setting("eval.val_sampler")
        steps = run.setting("eval.val_sampler_kwargs.steps")
        names.add(f"{sampler}{steps or ''}" if sampler else None)
    return names.pop() if len(names) == 1 else ", ".join(sorted(str(n) for n in names))


def _missing(by_task: dict[str, dict[str, list[Run]]]) -> list[str]:
    """The runs without test figures, and the re-scorings some of a method's runs have and others lack."""
    missing = []
    for by_policy in by_task.values():
        for runs in by_policy.values():
            names = sorted({n for r in runs for n in r.rescorings()})
            for r in runs:
                if not r.done:
                    missing.append(f"{r.name} (training)")
                missing += [f"{r.name} (re-scoring {n})" for n in names if n not in r.rescorings()]
    return missing


def finished_enough(by_task: dict[str, dict[str, list[Run]]], partial: bool) -> bool:
    """Whether to collect: every run and re-scoring finished, or ``partial`` (``--partial``) asked
    for what is; what is unfinished is listed on stderr either way."""
    missing = _missing(by_task)
    if missing:
        print("not finished:\n  " + "\n  ".join(missing), file=sys.stderr)
        if not partial:
            print("finish the grid (relaunch its command), or pass --partial", file=sys.stderr)
    return partial or not missing


def collect(runs: list[Run]) -> dict[str, dict[str, Any]]:
    """The ``tasks`` blocks of a success file from finished runs: task -> label -> figures."""
    by_task: dict[str, dict[str, list[Run]]] = {}
    for r in runs:
        by_task.setdefault(r.setting("task.name"), {}).setdefault(r.setting("policy.name"), []).append(r)
    results: dict[str, dict[str, Any]] = {}
    for task, by_policy in by_task.items():
        results[task] = {}
        for policy, all_runs in by_policy.items():
            done = sorted((r for r in all_runs if r.done), key=lambda r: r.setting("seed", 0))
            if not done:
                continue
            evaluations: dict[str, list[tuple[Run, dict[str, Any]]]] = {
                policy: [(r, r.result()) for r in done]
            }
            for name in sorted({n for r in done for n in r.rescorings()}):
                scored = [
                    (r, json.loads(r.rescorings()[name].read_text())) for r in done if name in r.rescorings()
                ]
                evaluations[f"{policy}_{name}"] = scored
            metric = headline_metric(evaluations[policy][0][1])
            curves = [[(e["step"], e.get(metric, e["success_once"])) for e in read_history(r)] for r in done]
            for label, scored in evaluations.items():
                own = label == policy
                results[task][label] = {
                    "metric": metric,
                    # the curve's sampler where it is not the method's own (None: its own)
                    "validation_sampler": _validation_sampler(done) if own else None,
                    "success_once": mean_and_spread([e["success_once"] for _, e in scored]),
                    metric: mean_and_spread([e[metric] for _, e in scored]),
                    "per_seed": [
                        {"seed": r.setting("seed"), **seed_record(e), **run_budget(r)} for r, e in scored
                    ],
                    "curves": curves if own else [],
                    "steps_to_90pct_of_best": [steps_to_fraction_of_best(c) for c in curves] if own else [],
                }
    return results


def grid_setting(task: str, runs: list[Run], roots: list[str]) -> dict[str, Any]:
    """The grid's setting for one task, read from its runs' configs (the report shows it)."""

    def common(dotted: str) -> Any:
        values = {json.dumps(r.setting(dotted)) for r in runs}
        return json.loads(values.pop()) if len(values) == 1 else sorted(json.loads(v) for v in values)

    rescored = {n for r in runs for n in r.rescorings()}
    return {
        "grids": roots,
        "tasks": [task],
        "policies": sorted({r.setting("policy.name") for r in runs}),
        "seeds": sorted({r.setting("seed") for r in runs}),
        "demos": common("demos.num"),
        "steps": common("train.steps"),
        "eval_every": common("train.eval_every"),
        "eval_episodes": common("eval.episodes"),
        "val_episodes": common("eval.val_episodes"),
        "maniskill_protocol": any(n.endswith("maniskill_protocol") for n in rescored),
        "extra": grid_extra(runs),
        # the machine in the file is where the runs were collected, not where they ran
        "collect_only": True,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "grids", nargs="+", help="grid folders (hydra.sweep.dir of l1flow-rl train -m +grid=...)"
    )
    parser.add_argument("--tag", default=None, help="results name (default: one file per task, by its name)")
    parser.add_argument("--plot", default=None, help="also draw the curves there (a PNG)")
    parser.add_argument("--partial", action="store_true", help="write what is finished; list what is not")
    parser.add_argument("--out-dir", default=str(RESULTS_DIR), help="where the results files go")
    parser.add_argument(
        "--quick", action="store_true", help="a check of a tiny grid: the file says so and is never reported"
    )
    args = parse_args(parser, argv)
    roots = [Path(g).as_posix() for g in args.grids]
    runs = [r for g in args.grids for r in grid_runs(g)]
    if not runs:
        print(f"no training runs under {', '.join(roots)} (a grid's hydra.sweep.dir)", file=sys.stderr)
        return 2
    by_task: dict[str, dict[str, list[Run]]] = {}
    for r in runs:
        by_task.setdefault(r.setting("task.name"), {}).setdefault(r.setting("policy.name"), []).append(r)
    if not finished_enough(by_task, args.partial):
        return 2
    results = collect(runs)
    saved = []
    for task, block in results.items():
        short = task.removeprefix("maniskill_")
        name = short if args.tag is None else args.tag if len(results) == 1 else f"{args.tag}_{short}"
        task_runs = [r for rs in by_task[task].values() for r in rs]
        figures = {
            "machine": machine_info(),
            "quick": args.quick,
            "args": grid_setting(task, task_runs, roots),
            "tasks": {task: block},
            "provenance": {**(provenance() or {}), "runs": grid_provenance(roots, task_runs)},
        }
        out = Path(args.out_dir) / f"success_{name}{'_quick' if args.quick else ''}.json"
        saved.append(save_results(out, figures))
    if args.plot:
        plot_success_curves(results, Path(args.plot))
    rows = [
        {
            "task": task,
            "method": label,
            "metric": b["metric"],
            "mean": b[b["metric"]]["mean"],
            "std": b[b["metric"]]["std"],
            "success_once": b["success_once"]["mean"],
            "seeds": b["success_once"]["n"],
            "steps to 90%": ",".join(str(s) for s in b["steps_to_90pct_of_best"]) or "-",
        }
        for task, block in results.items()
        for label, b in block.items()
    ]
    print(
        format_table(
            rows, ["task", "method", "metric", "mean", "std", "success_once", "seeds", "steps to 90%"]
        )
    )
    print("saved " + ", ".join(map(str, saved)) + (f" and {args.plot}" if args.plot else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
