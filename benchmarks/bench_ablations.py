"""The paper's ablations (its Tables 4-6) on one ManiSkill state task, at this machine's scale.

Every variant is a loss option (retrained) or a sampler swap (the same trained network re-scored):

* loss options, each trained over ``--seeds``: the L1 Flow default (x-space L1, mixed logit-normal t),
  MSE instead of L1, velocity-space loss instead of x-space, uniform t, Beta(1, 1.5) t;
* sampler swaps on the default network: t_first in 0.1 ... 0.9, and sample-prediction Euler with
  1, 2, 5 and 10 steps against the two-step schedule.

Saved: ``benchmarks/results/ablations_<task>.json`` (per variant: success_once mean and spread over
seeds, per-seed values with their 95 % intervals) and a PNG. Resumable like ``bench_success``.

    .venv/bin/python -m benchmarks.bench_ablations --task maniskill_pushcube --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from benchmarks.common import format_table, machine_info, save_results
from benchmarks.sweep import Run, mean_and_spread, rescore, seed_record, train

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
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not the claim")
    parser.add_argument("extra", nargs="*", help="hydra overrides applied to every run")
    args = parser.parse_args(argv)
    if args.quick:
        args.steps, args.eval_episodes, args.demos = 4, 1, 2
        args.extra = [*args.extra, "task.max_episode_steps=16"]
    root = Path(args.root) / args.task
    common = [
        f"task={args.task}",
        "policy=l1flow",
        f"demos.num={args.demos}",
        f"train.steps={args.steps}",
        f"eval.episodes={args.eval_episodes}",
        *args.extra,
    ]
    results: dict[str, Any] = {}
    default_runs: list[Run] = []
    for name, options in LOSS_VARIANTS.items():
        runs = [
            Run(f"{name}/seed{s}", [*common, f"seed={s}", *options], root / name / f"seed{s}")
            for s in args.seeds
        ]
        evals = [train(r, Path(args.root) / "data") for r in runs]
        results[name] = {"kind": "loss", "options": options, "evals": evals}
        if name == "default":
            default_runs = runs
    for name, overrides in SAMPLER_VARIANTS.items():
        task = [o for o in args.extra if o.startswith("task.")]  # re-scoring must see the same task
        evals = [
            rescore(r, name, [*overrides, f"eval.episodes={args.eval_episodes}", *task]) for r in default_runs
        ]
        results[name] = {"kind": "sampler", "options": overrides, "evals": evals}
    for block in results.values():
        evals = block.pop("evals")
        block["success_once"] = mean_and_spread([e["success_once"] for e in evals])
        block["per_seed"] = [seed_record(e) for e in evals]
    figures = {"machine": machine_info(), "quick": args.quick, "args": vars(args), "variants": results}
    out = Path("benchmarks/results") / f"ablations_{args.task}.json"
    if args.quick:
        out = Path(args.root) / f"ablations_{args.task}_quick.json"
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
