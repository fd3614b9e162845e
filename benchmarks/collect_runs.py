"""Record finished ``l1flow-rl train`` runs as a results file, from their own eval.json and summary.json.

For training runs made by hand (a task's default budget measured once), so that their figures reach
the README through ``benchmarks.report`` like every other result, not typed by hand.

    .venv/bin/python -m benchmarks.collect_runs --name training_robosuite RUN_DIR [RUN_DIR ...] [--note "..."]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks.common import machine_info, save_results

__all__ = ["main", "run_record"]


def run_record(run_dir: Path) -> dict:
    """Task, method, budget, wall time and test success (with its interval and seeds) of one run."""
    result = json.loads((run_dir / "eval.json").read_text())
    summary = json.loads((run_dir / "summary.json").read_text())
    return {
        "run_dir": str(run_dir),
        "task": summary["task"],
        "policy": summary["policy"],
        "demos": summary.get("demos"),
        "steps": summary.get("steps"),
        "demo_seconds": summary.get("demo_seconds"),
        "train_seconds": summary.get("train_seconds"),
        "wall_seconds": summary.get("wall_seconds"),
        "success_once": result["success_once"],
        "success_once_ci95": result.get("ci95", {}).get("success_once"),
        "success_at_end": result.get("success_at_end"),
        "episodes": result["episodes"],
        "split": result.get("split"),
        "split_seeds": result.get("split_seeds"),
        "chunk_latency_ms_median": result.get("latency_ms_median"),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--name", required=True, help="results/<name>.json")
    parser.add_argument("--note", default="", help="how the runs were made (load, budget)")
    parser.add_argument(
        "--results", type=Path, default=Path("benchmarks/results"), help="where <name>.json goes"
    )
    parser.add_argument("runs", nargs="+", type=Path)
    args = parser.parse_args(argv)
    missing = [
        str(r) for r in args.runs if not (r / "eval.json").is_file() or not (r / "summary.json").is_file()
    ]
    if missing:
        print(f"not finished runs (no eval.json/summary.json): {missing}", file=sys.stderr)
        return 2
    figures = {
        "machine": machine_info(),
        "note": args.note,
        "runs": [run_record(r) for r in args.runs],
    }
    out = save_results(args.results / f"{args.name}.json", figures)
    print(json.dumps(figures, indent=2))
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
