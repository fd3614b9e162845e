"""Saved fine-tuning results re-read under today's checkpoint rule, from their stored validations.

    python -m benchmarks.finetune.rechoose            # every benchmarks/results/finetune_online_*.json
    python -m benchmarks.finetune.rechoose --check    # exit 1 naming a file that is not re-read yet

A fine-tuning run ships the model that ``l1flow_rl.workspace.evaluator``'s ``"start"`` rule chooses:
the BC start (validated first) is kept unless a later model validates more than its standard error
above it. Runs measured under the earlier rule (any lead replaced the start) are re-chosen here without
a new simulation: the rule only ever moves a choice back to the start, whose test figure on the same
test seeds is the file's ``bc_start`` control. Such a seed's ``test`` becomes the start's, and its
measured pick stays beside it under ``rechosen``; the arm's mean and spread follow.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from benchmarks.finetune.bench_finetune_online import seeded_control
from benchmarks.lib.common import save_results
from benchmarks.lib.stats import runs_aggregate
from l1flow_rl.workspace.evaluator import choose_evaluation, rule_text

RESULTS = Path(__file__).resolve().parents[1] / "results"
HEADLINE = "success_once"


def _rechosen(record: dict[str, Any], start_test: dict[str, Any]) -> bool:
    """Re-choose one seed's run in place; True when its choice moved back to the start."""
    test = record.get("test") or {}
    selection = test.get("selection") or {}
    evaluations = selection.get("evaluations") or []
    if not evaluations or evaluations[0]["step"] != 0 or selection.get("step") in (None, 0):
        return False  # no stored start validation, or the start already chosen
    episodes = (selection.get("seeds") or {}).get("episodes")
    rows = [{**e, "episodes": episodes} for e in evaluations]
    if choose_evaluation(rows, HEADLINE, "start")["step"] != 0:
        return False
    p = rows[0][HEADLINE]
    record["rechosen"] = {
        "measured_pick": {
            "step": selection["step"],
            "validation": selection["value"],
            "test": test[HEADLINE],
        },
        "rule_then": selection.get("rule"),
    }
    rule = f"{rule_text(rows, HEADLINE, 'start')} (re-chosen from the stored validations)"
    record["test"] = {
        **{k: start_test.get(k) for k in ("success_once", "success_at_end", "episodes", "ci95")},
        "selection": {**selection, "step": 0, "value": p, "rule": rule},
    }
    return True


def rechoose(data: dict[str, Any]) -> list[str]:
    """Re-choose every fine-tuning run of one results file in place; the seeds that moved, named."""
    controls = data.get("controls") or {}
    start = (controls.get("bc_start") or {}).get("test")
    if start is None:
        return []
    moved = []
    for name, block in (data.get("algorithms") or {}).items():
        runs = block.get("runs") or {}
        changed = [s for s, r in runs.items() if _rechosen(r, start)]
        if changed:
            block["aggregate"] = runs_aggregate({int(s): r for s, r in runs.items()})
            moved += [f"{name} seed {s}" for s in changed]
    for name, block in controls.items():
        seeds = block.get("seeds") or {}
        if name == "bc_start" or name.endswith("_last") or not seeds:
            continue  # the start itself; last weights are no choice
        changed = [s for s, r in seeds.items() if _rechosen(r, start)]
        if changed:
            block.update(seeded_control({int(s): r for s, r in seeds.items()}))
            moved += [f"{name} seed {s}" for s in changed]
    return moved


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 if a file would change")
    args = parser.parse_args(argv)
    stale = []
    for path in sorted(args.results.glob("finetune_online_*.json")):
        data = json.loads(path.read_text())
        moved = rechoose(data)
        if not moved:
            continue
        stale.append(path.name)
        print(f"{path.name}: {', '.join(moved)} keep their start")
        if not args.check:
            save_results(path, data)  # the file keeps its provenance: when its runs were measured
    if args.check and stale:
        print(
            f"{len(stale)} file(s) not re-read under the start rule: python -m benchmarks.finetune.rechoose"
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
