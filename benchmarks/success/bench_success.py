"""Success and convergence, side by side (the paper's Table 2 and Figure 4 at this machine's scale).

For each task, each method (``policy=l1flow|flow|ddpm|regression``) is trained on the same
demonstrations with the same network over several seeds, evaluated every ``--eval-every`` steps on
the validation seeds, and finally on the test seeds. The DDPM network is also re-scored under
DDIM-16 (a sampler swap, no retraining), and with ``--maniskill-protocol`` every final network is
re-scored under ``eval.protocol=maniskill`` so the rows sit beside ManiSkill's published baseline.

Saved: ``benchmarks/results/success_<tag>.json`` (per run, per method: final success_once with its
95 % Wilson interval, mean and spread over seeds, the curve, steps to 90 % of the best); with
``--plot PATH``, the file's curves there too (the report draws every success file's curves in
``success_overview.png``). The sweep resumes:
finished runs are read back, interrupted ones continue from their last checkpoint. Several
invocations may split one grid (disjoint policies or seeds, one root); ``--collect-only`` then writes
the whole grid's file from their runs, training nothing.

Each row also carries the protocol's headline metric (PushT under ``eval.protocol=diffusion_policy``:
Diffusion Policy's score) and each run's budget (steps, wall and CPU seconds from its summary.json).

Budget on 2 CPU cores (state, default network, batch 64): about 9 training steps/s with both cores
(~5 on one), so 2,500 steps is ~5 minutes a run plus evaluations; 3 tasks x 4 methods x 3 seeds is
~2 h of training alone. ``--jobs N`` trains N runs side by side with cores/N threads each (a task's
demonstrations are made once first). ``--quick`` checks the script on tiny budgets.

    python -m benchmarks.success.bench_success --tasks maniskill_pushcube --seeds 0 1 2
    python -m benchmarks.success.bench_success --tasks pusht --policies l1flow flow regression --seeds 0 \
        --steps 8000 --eval-every 2000 --demos 200 --jobs 3 --tag pusht \
        data.padding=diffusion_policy eval.protocol=diffusion_policy eval.val_episodes=20
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from benchmarks.lib.common import format_table, machine_info, parse_args, save_results
from benchmarks.lib.sweep import (
    Run,
    headline_metric,
    make_demos,
    mean_and_spread,
    plot_success_curves,
    read_history,
    rescore,
    rescore_side_by_side,
    run_budget,
    seed_record,
    steps_to_fraction_of_best,
    train,
    train_side_by_side,
)

POLICIES = ("l1flow", "flow", "ddpm", "regression")
#: re-scorings of a finished network: name -> (policies it applies to, eval overrides)
RESCORES = {"ddim16": (("ddpm",), ["policy.sampler=ddim", "policy.sampler_kwargs.steps=16"])}
#: --ddpm-validation ddim16: DDPM runs validate (curve, checkpoint choice) under DDIM-16, a sixth of
#: DDPM-100's cost; their test figures stay DDPM-100 and the DDIM-16 re-scoring is unchanged
DDPM_VALIDATION = {"ddpm100": [], "ddim16": ["eval.val_sampler=ddim", "eval.val_sampler_kwargs.steps=16"]}


def _task_overrides(extra: list[str]) -> list[str]:
    """The task fields among the sweep's overrides, which re-scoring must see too."""
    return [o for o in extra if o.startswith("task.")]


def _rescore_plan(policy: str, args: argparse.Namespace) -> list[tuple[str, str, list[str]]]:
    """The re-scorings of one method's runs, as ``(label in the results, rescore name, eval
    overrides)``: its sampler swaps, then every evaluation again under ManiSkill's protocol."""
    task_fields = _task_overrides(args.extra)
    plan = [
        (f"{policy}_{name}", name, [*overrides, f"eval.episodes={args.eval_episodes}", *task_fields])
        for name, (policies, overrides) in RESCORES.items()
        if policy in policies
    ]
    if args.maniskill_protocol:
        for label in [policy, *(label for label, _, _ in plan)]:
            sampler = RESCORES.get(label.removeprefix(f"{policy}_"), ((), []))[1]
            plan.append(
                (
                    f"{label}_maniskill_protocol",
                    f"{label}_maniskill",
                    [*sampler, "eval.protocol=maniskill", *task_fields],
                )
            )
    return plan


def _train_side_by_side(grid: dict[str, dict[str, list[Run]]], args: argparse.Namespace, root: Path) -> None:
    """Train the grid's unfinished runs ``args.jobs`` at a time; each task's demonstrations are made
    first, once, since runs sharing a file must not make it together."""
    for task, by_policy in grid.items():
        first = next(iter(by_policy.values()))[0]
        shared = [o for o in first.overrides if o.startswith(("task", "demos."))]
        make_demos(shared, root / "data", root / task / "demos.log")
    runs = [r for by_policy in grid.values() for task_runs in by_policy.values() for r in task_runs]
    train_side_by_side(runs, root / "data", args.jobs)


def _missing(
    grid: dict[str, dict[str, list[Run]]], plans: dict[str, dict[str, list[tuple[str, str, list[str]]]]]
) -> list[str]:
    """The grid's runs and re-scorings that have no eval.json yet."""
    missing = []
    for task, by_policy in grid.items():
        for policy, runs in by_policy.items():
            for r in runs:
                if not r.done:
                    missing.append(f"{r.name} (training)")
                missing += [
                    f"{r.name} (re-scoring {name})"
                    for _, name, _ in plans[task][policy]
                    if not (r.run_dir / f"rescore_{name}" / "eval.json").is_file()
                ]
    return missing


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["maniskill_pushcube"])
    parser.add_argument("--plot", default=None, help="also draw the curves there (a PNG)")
    parser.add_argument("--policies", nargs="+", default=list(POLICIES))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=2500)
    parser.add_argument("--eval-every", type=int, default=500)
    parser.add_argument("--eval-episodes", type=int, default=50)
    parser.add_argument("--demos", type=int, default=100)
    parser.add_argument(
        "--maniskill-protocol", action="store_true", help="also score under eval.protocol=maniskill"
    )
    parser.add_argument(
        "--ddpm-validation",
        choices=sorted(DDPM_VALIDATION),
        default="ddpm100",
        help="the sampler of DDPM runs' validation curve (ddim16: a sixth of the cost; test stays DDPM-100)",
    )
    parser.add_argument("--root", default="runs/bench_success", help="where the runs and data live")
    parser.add_argument("--tag", default=None, help="results name (default: the task list)")
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="runs trained side by side, each with cores/jobs torch threads (small networks use several "
        "cores poorly, so 2-3 jobs on 2 cores finish a grid sooner; each run's CPU time is recorded)",
    )
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not the claim")
    parser.add_argument(
        "--collect-only",
        action="store_true",
        help="train and re-score nothing: write the results of runs finished by earlier invocations "
        "(several invocations splitting one grid, or runs copied from other machines); "
        "exit 2 listing every run or re-scoring still missing",
    )
    parser.add_argument("extra", nargs="*", help="hydra overrides applied to every run")
    args = parse_args(parser, argv)
    if args.quick:
        args.steps, args.eval_every, args.eval_episodes, args.demos = 4, 2, 1, 2
        args.extra = [*args.extra, "task.max_episode_steps=16"]
    root = Path(args.root)
    tag = args.tag or "_".join(t.replace("maniskill_", "") for t in args.tasks)
    grid: dict[str, dict[str, list[Run]]] = {}
    for task in args.tasks:
        grid[task] = {}
        for policy in args.policies:
            grid[task][policy] = [
                Run(
                    f"{task}/{policy}/seed{seed}",
                    [
                        f"task={task}",
                        f"policy={policy}",
                        f"seed={seed}",
                        f"demos.num={args.demos}",
                        f"train.steps={args.steps}",
                        f"train.eval_every={args.eval_every}",
                        f"train.checkpoint_every={args.eval_every}",
                        f"eval.episodes={args.eval_episodes}",
                        *(DDPM_VALIDATION[args.ddpm_validation] if policy == "ddpm" else []),
                        *args.extra,
                    ],
                    root / task / policy / f"seed{seed}",
                )
                for seed in args.seeds
            ]
    plans = {task: {p: _rescore_plan(p, args) for p in by_policy} for task, by_policy in grid.items()}
    if args.collect_only:
        missing = _missing(grid, plans)
        if missing:
            print("--collect-only: not finished:\n  " + "\n  ".join(missing), file=sys.stderr)
            return 2
    if args.jobs > 1:
        _train_side_by_side(grid, args, root)
    if args.jobs > 1:  # re-scorings side by side too; the loop below then reads them back
        rescore_side_by_side(
            [
                (r, name, o)
                for t in grid
                for p, runs in grid[t].items()
                for _, name, o in plans[t][p]
                for r in runs
            ],
            args.jobs,
        )
    results: dict[str, Any] = {}
    for task, by_policy in grid.items():
        results[task] = {}
        for policy, runs in by_policy.items():
            # each run's re-scorings follow its training: a sweep stopped midway leaves whole runs,
            # whose records can be kept without their checkpoints
            evaluations: dict[str, list[dict[str, Any]]] = {
                label: [] for label in [policy, *(label for label, _, _ in plans[task][policy])]
            }
            for r in runs:
                evaluations[policy].append(train(r, root / "data"))
                for label, name, overrides in plans[task][policy]:
                    evaluations[label].append(rescore(r, name, overrides))
            metric = headline_metric(evaluations[policy][0])
            curves = [[(e["step"], e.get(metric, e["success_once"])) for e in read_history(r)] for r in runs]
            for label, evals in evaluations.items():
                finals = [e["success_once"] for e in evals]
                results[task][label] = {
                    "metric": metric,
                    # the curve's sampler where it is not the method's own (None: its own)
                    "validation_sampler": "ddim16"
                    if policy == "ddpm" and label == policy and args.ddpm_validation == "ddim16"
                    else None,
                    "success_once": mean_and_spread(finals),
                    metric: mean_and_spread([e[metric] for e in evals]),
                    "per_seed": [{**seed_record(e), **run_budget(r)} for e, r in zip(evals, runs)],
                    "curves": curves if label == policy else [],
                    "steps_to_90pct_of_best": [steps_to_fraction_of_best(c) for c in curves]
                    if label == policy
                    else [],
                }
    figures = {"machine": machine_info(), "quick": args.quick, "args": vars(args), "tasks": results}
    out = Path("benchmarks/results") / f"success_{tag}{'_quick' if args.quick else ''}.json"
    if args.quick:
        out = root / out.name
    save_results(out, figures)
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
    print(f"saved {out}" + (f" and {args.plot}" if args.plot else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
