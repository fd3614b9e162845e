"""The PushT planner over many seeds: success (coverage > 0.95), Diffusion Policy's score, steps and
seconds per episode, and the share of episodes that went around the block on each side. Prints and
saves ``benchmarks/results/pusht_expert.json``. ``--quick`` runs a couple of seeds in this process to
check the script end to end and saves ``pusht_expert_quick.json`` unless ``--out`` says otherwise.

    python -m benchmarks.success.bench_pusht_expert --seeds 100 --workers 2 [--quick] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from benchmarks.lib.common import RESULTS_DIR, machine_info, parse_args, save_results

DEFAULT_OUT = RESULTS_DIR / "pusht_expert.json"
#: where --quick saves without --out: beside the real file, never over it
QUICK_OUT = DEFAULT_OUT.with_name("pusht_expert_quick.json")
#: --quick: seeds, run in this process (a worker pool only adds start-up time)
QUICK_SEEDS, QUICK_WORKERS = 2, 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default=None, help=f"default: {DEFAULT_OUT} ({QUICK_OUT.name} with --quick)")
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not speed")
    args = parse_args(parser, argv)
    if args.quick:
        args.seeds, args.workers = QUICK_SEEDS, QUICK_WORKERS
    out = Path(args.out or (QUICK_OUT if args.quick else DEFAULT_OUT))
    from l1flow_rl.experts.pusht.demos import run_episodes

    start, load_before = time.perf_counter(), os.getloadavg()
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    rows = []
    for seed, demo, error in run_episodes(seeds, workers=args.workers, desc="PushT planner"):
        if demo is None:
            rows.append(
                {"seed": seed, "success": False, "score": 0.0, "error": error or "no reproducible start"}
            )
            continue
        rows.append(
            {
                "seed": seed,
                "success": bool(demo.success),
                "score": demo.score,
                "steps": demo.steps,
                "seconds": demo.seconds,
                "side": demo.side,
            }
        )
    wall = time.perf_counter() - start
    ran = [r for r in rows if "steps" in r]
    sides = [r["side"] for r in ran]
    result = {
        "quick": args.quick,
        "seeds": len(rows),
        "first_seed": args.first_seed,
        "success": float(np.mean([r["success"] for r in rows])),
        "mean_score": float(np.mean([r["score"] for r in rows])),
        "steps_mean": float(np.mean([r["steps"] for r in ran])),
        "seconds_per_episode_mean": float(np.mean([r["seconds"] for r in ran])),
        "side_share": {s: sides.count(s) / len(sides) for s in ("left", "right", "none")},
        "side_share_of_chosen": {
            s: sides.count(s) / max(1, sides.count("left") + sides.count("right")) for s in ("left", "right")
        },
        "success_by_side": {
            s: float(np.mean([r["success"] for r in ran if r["side"] == s])) if s in sides else None
            for s in ("left", "right", "none")
        },
        "wall_seconds": wall,
        "workers": args.workers,
        "loadavg_before": load_before,
        "loadavg_after": os.getloadavg(),
        "cpu_count": os.cpu_count(),
        "machine": machine_info(),
        "per_seed": rows,
    }
    save_results(out, result)
    print(json.dumps({k: v for k, v in result.items() if k != "per_seed"}, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
