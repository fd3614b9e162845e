"""The MLP denoiser against the UNet on the same tasks and data: success, convergence and cost.

The MLP's side is a success grid run with ``network=mlp`` (L1 Flow only; its last weights re-scored
too); the UNet's side is the published L1 Flow figures of the same task (``success_<task>.json``,
written by ``bench_success``), so both come from the same demonstrations and protocol code::

    l1flow-rl train -m +grid=success_maniskill policy=l1flow network=mlp \\
        hydra.sweep.dir=runs/grid/success_maniskill_mlp
    l1flow-rl eval -m +grid=success_maniskill +rescore=last_weights policy=l1flow \\
        hydra.sweep.dir=runs/grid/success_maniskill_mlp   # the network comes from the checkpoints
    python -m benchmarks.success.bench_networks runs/grid/success_*_mlp

Saved: ``benchmarks/results/network_success.json``, per task: the MLP's block (as ``bench_success``
collects it: per seed test figures, curves, steps to 90 % of best, budgets with the training phase's
seconds), its last weights' test, and the UNet block it is compared with, copied with its file's name and
setting. The UNet file chosen for a task: the same number of demonstrations, then
the most seeds, then the training steps closest to the MLP's. Trains nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from benchmarks.lib.common import RESULTS_DIR, machine_info, parse_args, provenance, save_results
from benchmarks.lib.runs import grid_provenance, grid_runs
from benchmarks.success.bench_success import collect, finished_enough, grid_setting

__all__ = ["main", "published_success", "unet_reference"]

#: the method both networks are compared on
METHOD = "l1flow"


def published_success(results: Path) -> list[tuple[str, dict[str, Any]]]:
    """(name, data) of every measured success file under ``results`` (``--quick`` checks left out)."""
    found = [(p.name, json.loads(p.read_text())) for p in sorted(results.glob("success_*.json"))]
    return [(name, data) for name, data in found if not data.get("quick")]


def unet_reference(
    task: str, demos: int, steps: int, published: list[tuple[str, dict[str, Any]]]
) -> dict[str, Any] | None:
    """The published UNet L1 Flow figures of ``task`` to compare the MLP with: among the success files
    with that task's L1 Flow block on the UNet and ``demos`` demonstrations, the most seeds, then the
    steps closest to ``steps``. None when no file qualifies."""
    candidates = []
    for name, data in published:
        args = data.get("args") or {}
        block = (data.get("tasks") or {}).get(task, {}).get(METHOD)
        on_unet = not any(o.startswith(("network=", "network.name=")) for o in args.get("extra") or [])
        if block is None or not on_unet or args.get("demos") != demos:
            continue
        seeds = block["success_once"]["n"]
        candidates.append(((-seeds, abs(args["steps"] - steps), name), data, block))
    if not candidates:
        return None
    (_, _, name), data, block = min(candidates, key=lambda c: c[0])
    return {"file": name, "args": data.get("args"), "block": block}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("grids", nargs="+", help="the MLP grids' folders (hydra.sweep.dir)")
    parser.add_argument("--partial", action="store_true", help="write what is finished; list what is not")
    parser.add_argument("--out-dir", default=str(RESULTS_DIR), help="where network_success.json goes")
    parser.add_argument(
        "--results", default=str(RESULTS_DIR), help="where the UNet's success files are read from"
    )
    args = parse_args(parser, argv)
    roots = [Path(g).as_posix() for g in args.grids]
    runs = [r for g in args.grids for r in grid_runs(g) if r.setting("policy.name") == METHOD]
    off_network = sorted({r.name for r in runs if r.setting("network.name") != "mlp"})
    if not runs or off_network:
        problem = f"runs not on network=mlp: {', '.join(off_network)}" if off_network else "no L1 Flow runs"
        print(f"{', '.join(roots)}: {problem} (an MLP grid's hydra.sweep.dir)", file=sys.stderr)
        return 2
    by_task: dict[str, dict[str, list]] = {}
    for r in runs:
        by_task.setdefault(r.setting("task.name"), {}).setdefault(METHOD, []).append(r)
    if not finished_enough(by_task, args.partial):
        return 2
    published, tasks = published_success(Path(args.results)), {}
    for task, block in collect(runs).items():
        setting = grid_setting(task, by_task[task][METHOD], roots)
        reference = unet_reference(task, setting["demos"], setting["steps"], published)
        if reference is None:
            print(f"{task}: no published UNet L1 Flow figures with {setting['demos']} demos", file=sys.stderr)
            return 2
        tasks[task] = {"args": setting, "mlp": block, "unet": reference}
    figures = {
        "machine": machine_info(),
        "quick": False,
        "tasks": tasks,
        "provenance": {**(provenance() or {}), "runs": grid_provenance(roots, runs)},
    }
    out = save_results(Path(args.out_dir) / "network_success.json", figures)
    for task, t in tasks.items():
        mlp, unet = t["mlp"][METHOD], t["unet"]["block"]
        print(
            f"{task}: MLP {mlp['success_once']['mean']:.3f} ({t['args']['steps']:,} steps) against UNet "
            f"{unet['success_once']['mean']:.3f} ({t['unet']['args']['steps']:,} steps, {t['unet']['file']})"
        )
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
