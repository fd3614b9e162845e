"""Scripted robosuite experts: success rate over many seeds and seconds per episode, per task.

Each episode runs in this process on one env without cameras (what ``l1flow-rl demos`` runs in each
worker), from the scene of its seed (0, 1, ...), up to the task's ``max_episode_steps``. ``--quick``
runs one seed per task to check the script end to end and saves ``robosuite_experts_quick.json``
unless ``--out`` says otherwise.

    python -m benchmarks.success.bench_robosuite_experts [--seeds 100] [--tasks robosuite_lift ...]
    python -m benchmarks.success.bench_robosuite_experts --quick [--out PATH]

Rows of tasks not run this time are kept from the file being written (each row carries its own
machine figures), so one task can be measured again without re-running the others.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from benchmarks.lib.common import format_table, machine_info, parse_args, save_results
from l1flow_rl.config import load_task_config

DEFAULT_OUT = "benchmarks/results/robosuite_experts.json"
#: where --quick saves without --out: beside the real file, never over it
QUICK_OUT = "benchmarks/results/robosuite_experts_quick.json"
#: --quick: seeds per task (every task still runs: each has its own expert)
QUICK_SEEDS = 1


def run_task(name: str, seeds: int) -> dict:
    from l1flow_rl.envs.robosuite import sim

    from l1flow_rl.experts.robosuite.demos import run_episode

    task = load_task_config(name)
    env = sim.make_from_env_args(sim.env_args_for_task(task, cameras=[]), source=name)
    seconds, lengths, failed = [], [], []
    for seed in range(seeds):
        start = time.perf_counter()
        demo = run_episode(env, task, seed)
        seconds.append(time.perf_counter() - start)
        if demo is None:
            failed.append(seed)
        else:
            lengths.append(len(demo["actions"]))
    env.close()
    row = {
        "task": name,
        "env_id": task.env_id,
        "seeds": seeds,
        "success_rate": (seeds - len(failed)) / seeds,
        "seconds_per_episode": round(statistics.mean(seconds), 3),
        "steps_per_success_mean": round(statistics.mean(lengths), 1) if lengths else None,
        "steps_per_success_max": max(lengths) if lengths else None,
        "failed_seeds": failed,
    }
    print(row, flush=True)
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument(
        "--tasks",
        nargs="*",
        default=["robosuite_lift", "robosuite_stack", "robosuite_can", "robosuite_square"],
    )
    parser.add_argument("--out", default=None, help=f"default: {DEFAULT_OUT} ({QUICK_OUT} with --quick)")
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not speed")
    args = parse_args(parser, argv)
    if args.quick:
        args.seeds = QUICK_SEEDS
    torch.set_num_threads(1)
    out_path = Path(args.out or (QUICK_OUT if args.quick else DEFAULT_OUT))
    machine_start = machine_info()
    rows = []
    for name in args.tasks:
        start = machine_info()
        rows.append(
            {**run_task(name, args.seeds), "machine_at_start": start, "machine_at_end": machine_info()}
        )
    if out_path.is_file():
        kept = [r for r in json.loads(out_path.read_text())["rows"] if r["task"] not in args.tasks]
        rows = kept + rows
    print(
        format_table(rows, ["task", "seeds", "success_rate", "seconds_per_episode", "steps_per_success_mean"])
    )
    figures = {"quick": args.quick, "machine_at_start": machine_start, "machine_at_end": machine_info()}
    out = save_results(out_path, {**figures, "rows": rows})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
