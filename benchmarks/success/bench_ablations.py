"""The paper's ablations (its Tables 4-6) on one ManiSkill state task, at this machine's scale,
collected from an ablation grid's runs.

Every variant is a loss option (retrained) or a sampler swap (the same trained network re-scored):

* loss options, each trained over the grid's seeds (``configs/grid/ablation/``): the L1 Flow default
  (x-space L1, mixed logit-normal t), MSE instead of L1, velocity-space loss instead of x-space,
  uniform t, Beta(1, 1.5) t;
* sampler swaps on the default network (``configs/rescore/ablation_*.yaml``): t_first in 0.1 ... 0.9,
  and sample-prediction Euler with 1, 2, 5 and 10 steps against the two-step schedule.

The grid is a hydra multirun, run with any launcher and resumable like every grid::

    l1flow-rl train -m +grid=ablations_pushcube
    l1flow-rl eval -m +grid=ablations_pushcube +rescore=ablation_t_first
    l1flow-rl eval -m +grid=ablations_pushcube +rescore=ablation_euler
    python -m benchmarks.success.bench_ablations runs/grid/ablations_pushcube

Saved: ``benchmarks/results/ablations_<task>_<demos>demos_<steps>steps.json`` (per variant:
success_once mean and spread over seeds, per-seed values with their 95 % intervals; the runs'
commits, launchers and config under ``provenance.runs``) and a PNG. Pick a setting below the
ceiling, or every variant ties: PushCube with 100 demonstrations saturates near 0.9 in 2,500 steps.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from benchmarks.lib.common import (
    RESULTS_DIR,
    format_table,
    machine_info,
    parse_args,
    provenance,
    save_results,
)
from benchmarks.lib.runs import Run, grid_provenance, grid_runs, seed_record
from benchmarks.lib.stats import mean_and_spread
from l1flow_rl.workspace.checkpoint import flatten_config

__all__ = ["main", "variants"]

#: the grid's config group of loss variants (``configs/grid/ablation/<name>.yaml``)
VARIANT_GROUP = "+grid/ablation"


def _variant(run: Run) -> str:
    """A run's loss variant: its ``+grid/ablation=<name>`` override, else its folder's first part."""
    for o in run.overrides:
        if o.startswith(f"{VARIANT_GROUP}="):
            return o.split("=", 1)[1]
    return run.name.split("/", 1)[0]


def _natural(name: str) -> tuple:
    """Sort key: letters, then the number a name ends with (euler2 before euler10)."""
    head = name.rstrip("0123456789.")
    tail = name[len(head) :]
    try:
        return (head, float(tail))
    except ValueError:
        return (head, 0.0)


def _options(run: Run, default: Run | None) -> list[str]:
    """What a loss variant's runs change against the default's: ``key=value`` of every ``policy.``
    field that differs."""
    if default is None:
        return []
    a = flatten_config(run.config.get("policy") or {}, "policy.")
    b = flatten_config(default.config.get("policy") or {}, "policy.")
    return [f"{k}={v}" for k, v in sorted(a.items()) if b.get(k) != v]


def variants(runs: list[Run]) -> tuple[dict[str, Any], list[str]]:
    """(variant -> {kind, options, evals}, what is missing) from an ablation grid's runs: each loss
    variant's test figures, then each re-scoring of the default's networks."""
    by_variant: dict[str, list[Run]] = {}
    for r in runs:
        by_variant.setdefault(_variant(r), []).append(r)
    missing = [f"{r.name} (training)" for r in runs if not r.done]
    default_runs = sorted(by_variant.get("default", []), key=lambda r: r.setting("seed", 0))
    found: dict[str, Any] = {}
    for name in sorted(by_variant, key=lambda n: n != "default"):  # the default first, then launch order
        done = sorted((r for r in by_variant[name] if r.done), key=lambda r: r.setting("seed", 0))
        if done:
            options = _options(done[0], default_runs[0] if default_runs else None)
            found[name] = {"kind": "loss", "options": options, "evals": [r.result() for r in done]}
    swaps = sorted({n for r in default_runs for n in r.rescorings()}, key=_natural)
    for swap in swaps:
        scored = [r for r in default_runs if swap in r.rescorings()]
        missing += [f"{r.name} (re-scoring {swap})" for r in default_runs if r not in scored]
        evals = [json.loads(r.rescorings()[swap].read_text()) for r in scored]
        sampler = evals[0].get("sampler") or {}
        options = [f"policy.sampler={sampler.get('name')}"]
        options += [f"policy.sampler_kwargs.{k}={v}" for k, v in (sampler.get("kwargs") or {}).items()]
        found[swap] = {"kind": "sampler", "options": options, "evals": evals}
    return found, missing


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
    parser.add_argument("grid", help="the grid's folder (hydra.sweep.dir of l1flow-rl train -m +grid=...)")
    parser.add_argument("--partial", action="store_true", help="write what is finished; list what is not")
    parser.add_argument("--out-dir", default=str(RESULTS_DIR), help="where the results file goes")
    parser.add_argument(
        "--quick", action="store_true", help="a check of a tiny grid: the file says so and is never reported"
    )
    args = parse_args(parser, argv)
    runs = grid_runs(args.grid)
    if not runs:
        print(f"no training runs under {args.grid} (a grid's hydra.sweep.dir)", file=sys.stderr)
        return 2
    results, missing = variants(runs)
    if missing:
        print("not finished:\n  " + "\n  ".join(missing), file=sys.stderr)
        if not args.partial:
            print("finish the grid (relaunch its commands), or pass --partial", file=sys.stderr)
            return 2
    for block in results.values():
        evals = block.pop("evals")
        block["success_once"] = mean_and_spread([e["success_once"] for e in evals])
        block["per_seed"] = [seed_record(e) for e in evals]
    first = runs[0]
    setting = {
        "grid": Path(args.grid).as_posix(),
        "task": first.setting("task.name"),
        "seeds": sorted({r.setting("seed") for r in runs}),
        "steps": first.setting("train.steps"),
        "eval_episodes": first.setting("eval.episodes"),
        "demos": first.setting("demos.num"),
    }
    name = f"{setting['task']}_{setting['demos']}demos_{setting['steps']}steps"
    figures = {
        "machine": machine_info(),
        "quick": args.quick,
        "args": setting,
        "variants": results,
        "provenance": {**(provenance() or {}), "runs": grid_provenance([args.grid], runs)},
    }
    out = Path(args.out_dir) / f"ablations_{name}{'_quick' if args.quick else ''}.json"
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
