"""The paper's ablations (its Tables 4-6) on one ManiSkill state task, at this machine's scale.

Every variant is a loss option (retrained) or a sampler swap (the same trained network re-scored):

* loss options, each trained over ``--seeds``: the L1 Flow default (x-space L1, mixed logit-normal t),
  MSE instead of L1, velocity-space loss instead of x-space, uniform t, Beta(1, 1.5) t;
* sampler swaps on the default network: t_first in 0.1 ... 0.9, and sample-prediction Euler with
  1, 2, 5 and 10 steps against the two-step schedule.

Saved: ``benchmarks/results/ablations_<task>_<demos>demos_<steps>steps.json`` (per variant:
success_once mean and spread over seeds, per-seed values with their 95 % intervals) and a PNG. Runs
live under ``--root``/<the same setting name>/ and resume like ``bench_success``'s; ``--jobs N`` trains
N loss variants, then re-scores N sampler swaps, side by side; one job re-scores each default run
right after training it, so that a stopped sweep leaves whole runs.
Pick a setting below the ceiling, or every variant ties: PushCube with 100 demonstrations saturates
near 0.9 in 2,500 steps.

    python -m benchmarks.success.bench_ablations --task maniskill_pushcube --demos 20 --seeds 0 1 2 --jobs 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from benchmarks.lib.common import format_table, machine_info, parse_args, save_results
from benchmarks.lib.sweep import (
    Run,
    make_demos,
    mean_and_spread,
    rescore,
    rescore_side_by_side,
    seed_record,
    train,
    train_side_by_side,
)

#: retrained variants: name -> loss options (policy=l1flow otherwise)
LOSS_VARIANTS: dict[str, list[str]] = {
    "default": [],
    "mse": ["policy.loss_kwargs.loss_type=mse"],
    "v_space_loss": ["policy.loss_kwargs.loss_space=v"],
    "uniform_t": ["policy.loss_kwargs.timesteps=uniform"],
    "beta_t": ["policy.loss_kwargs.timesteps=beta"],
}
#: sampler swaps on the default network: name -> eval overrides
SAMPLER_VARIANTS: dict[str, list[str]] = {
    **{
        f"t_first_{t}": ["policy.sampler=two_step", f"policy.sampler_kwargs.t_first={t}"]
        for t in (0.1, 0.3, 0.5, 0.7, 0.9)
    },
    **{f"euler{k}": ["policy.sampler=euler", f"policy.sampler_kwargs.steps={k}"] for k in (1, 2, 5, 10)},
}


def _plot(results: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    means = [results[n]["success_once"]["mean"] for n in names]
    stds = [results[n]["success_once"]["std"] for n in names]
    fig, ax = plt.subplots(figsize=(max(6, 0.6 * len(names)), 3.6))
    ax.bar(range(len(names)), means, yerr=stds, capsize=3, color="tab:blue", alpha=0.8)
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right", fontsize=8)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("success_once (test seeds)")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="maniskill_pushcube")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=2500)
    parser.add_argument("--eval-episodes", type=int, default=50)
    parser.add_argument("--demos", type=int, default=100)
    parser.add_argument("--root", default="runs/bench_ablations")
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="loss variants trained side by side, cores/jobs torch threads each (as bench_success)",
    )
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not the claim")
    parser.add_argument("extra", nargs="*", help="hydra overrides applied to every run")
    args = parse_args(parser, argv)
    if args.quick:
        args.steps, args.eval_episodes, args.demos = 4, 1, 2
        args.extra = [*args.extra, "task.max_episode_steps=16"]
    # the setting names the folder: runs of another demonstration count are never read back as these
    setting = f"{args.task}_{args.demos}demos_{args.steps}steps"
    root = Path(args.root) / setting
    common = [
        f"task={args.task}",
        "policy=l1flow",
        f"demos.num={args.demos}",
        f"train.steps={args.steps}",
        f"eval.episodes={args.eval_episodes}",
        *args.extra,
    ]
    results: dict[str, Any] = {}
    data_dir = Path(args.root) / "data"
    grid = {
        name: [
            Run(f"{name}/seed{s}", [*common, f"seed={s}", *options], root / name / f"seed{s}")
            for s in args.seeds
        ]
        for name, options in LOSS_VARIANTS.items()
    }
    default_runs = grid["default"]
    task = [o for o in args.extra if o.startswith("task.")]  # re-scoring must see the same task
    swaps = {n: [*o, f"eval.episodes={args.eval_episodes}", *task] for n, o in SAMPLER_VARIANTS.items()}
    if args.jobs > 1:
        make_demos([o for o in common if o.startswith(("task", "demos."))], data_dir, root / "demos.log")
        train_side_by_side([r for runs in grid.values() for r in runs], data_dir, args.jobs)
        # side by side first; the loops below read them back
        rescore_side_by_side([(r, n, o) for n, o in swaps.items() for r in default_runs], args.jobs)
    for name, runs in grid.items():
        evals = []
        for r in runs:
            evals.append(train(r, data_dir))
            if name == "default":  # its swaps right away: a stopped sweep leaves whole runs
                for swap, overrides in swaps.items():
                    rescore(r, swap, overrides)
        results[name] = {"kind": "loss", "options": LOSS_VARIANTS[name], "evals": evals}
    for name, overrides in swaps.items():
        evals = [rescore(r, name, overrides) for r in default_runs]
        results[name] = {"kind": "sampler", "options": SAMPLER_VARIANTS[name], "evals": evals}
    for block in results.values():
        evals = block.pop("evals")
        block["success_once"] = mean_and_spread([e["success_once"] for e in evals])
        block["per_seed"] = [seed_record(e) for e in evals]
    figures = {"machine": machine_info(), "quick": args.quick, "args": vars(args), "variants": results}
    out = Path("benchmarks/results") / f"ablations_{setting}.json"
    if args.quick:
        out = Path(args.root) / f"ablations_{setting}_quick.json"
    save_results(out, figures)
    _plot(results, out.with_suffix(".png"))
    rows = [
        {
            "variant": n,
            "kind": b["kind"],
            "success_once": b["success_once"]["mean"],
            "std": b["success_once"]["std"],
        }
        for n, b in results.items()
    ]
    print(format_table(rows, ["variant", "kind", "success_once", "std"]))
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
