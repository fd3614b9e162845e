"""Online fine-tuning from one BC checkpoint: each algorithm's preset (``configs/finetune/``), one run each,
then success against env steps and the cost figures of every run in one JSON and one figure.

    .venv/bin/python -m benchmarks.bench_finetune_online --checkpoint runs/bc/checkpoints/best.pt \\
        --task maniskill_pushcube --steps 15000 --jobs 3

The runs are ``l1flow-rl finetune finetune=<algorithm> ...`` with the preset's defaults, except the
per-algorithm budget overrides in :data:`CPU_BUDGET` (each says why: what the 2-core cost figures of
``bench_finetune_cost.py`` allow); ``--override`` adds more to every run. ``--collect-only`` reads
finished runs again.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from benchmarks.common import machine_info, save_results

#: budget departures from the presets on 2 shared CPU cores, with the cost figure that forces each
CPU_BUDGET: dict[str, list[str]] = {
    # an update with 32 proposals at batch 256 takes 14-34 s here (N=8: 3 s): N=8 and 1 update per 20 steps
    "qc": ["finetune.qc.num_samples=8", "online.updates_per_step=0.05"],
    # an update takes 0.77 s (BC + the 2-NFE teacher): 1 update per 4 env steps
    "fql": ["online.updates_per_step=0.25"],
    # an update takes 0.09 s (no flow call): the preset's UTD 1
    "dsrl": [],
}


def run_one(algorithm: str, args, run_dir: Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "l1flow_rl.cli",
        "finetune",
        f"finetune={algorithm}",
        f"checkpoint={args.checkpoint}",
        f"task={args.task}",
        f"run_dir={run_dir}",
        f"online.steps={args.steps}",
        f"online.eval_every={args.eval_every}",
        f"eval.episodes={args.test_episodes}",
        f"eval.val_episodes={args.val_episodes}",
        f"seed={args.seed}",
        *CPU_BUDGET[algorithm],
        *args.override,
    ]


def read_run(run_dir: Path) -> dict:
    """A finished run's figures; a run stopped early (no eval.json) is read from its last checkpoint."""
    stopped = not (run_dir / "eval.json").is_file()
    if stopped:
        from l1flow_rl.workspace.checkpoint import load_checkpoint

        state = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
        history = {"evals": state["evals"], "rounds": state["records"].get("rounds", [])}
        summary = {**state["progress"], "machine": None}
        test = {}
    else:
        history = json.loads((run_dir / "history.json").read_text())
        summary = json.loads((run_dir / "summary.json").read_text())
        test = json.loads((run_dir / "eval.json").read_text())
    val = [e for e in history["evals"] if e.get("split", "val") == "val"]
    rounds = history.get("rounds", [])
    trained = [r for r in rounds if r.get("policy") == "actor"]

    def mean(key, rows):
        values = [r[key] for r in rows if r.get(key) is not None]
        return sum(values) / len(values) if values else None

    return {
        "stopped_early": stopped,
        "validation": [
            {
                "env_steps": e.get("env_steps", 0),
                "phase": e.get("phase", "final"),
                "success_once": e["success_once"],
            }
            for e in val
        ],
        "collected_success": [[r["env_steps"], r.get("episode_success")] for r in rounds],
        "test": {k: test.get(k) for k in ("success_once", "success_at_end", "episodes", "ci95", "selection")},
        "start_validation": val[0]["success_once"] if val else None,
        "env_steps_per_s_warmup": mean("env_steps_per_s", [r for r in rounds if r.get("policy") == "start"]),
        "env_steps_per_s_actor": mean("env_steps_per_s", trained),
        "updates_per_s": mean("updates_per_s", trained),
        "summary": {
            k: summary.get(k)
            for k in ("online_updates", "env_steps", "wall_seconds", "cpu_seconds", "online_seconds")
        },
        "machine": summary.get("machine"),
    }


def plot(results: dict, task: str, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for name, r in results.items():
        val = r["validation"]
        ax.plot(
            [v["env_steps"] for v in val],
            [v["success_once"] for v in val],
            "o-",
            label=f"{name} (validation)",
        )
    ax.set_xlabel("environment steps")
    ax.set_ylabel("success rate")
    ax.set_ylim(-0.05, 1.05)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"online fine-tuning from one BC start, {task} (1 seed)")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--task", default="maniskill_pushcube")
    parser.add_argument("--algorithms", nargs="+", default=list(CPU_BUDGET))
    parser.add_argument("--steps", type=int, default=15000)
    parser.add_argument("--eval-every", type=int, default=5000)
    parser.add_argument("--val-episodes", type=int, default=50)
    parser.add_argument("--test-episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=1, help="runs at once")
    parser.add_argument("--root", default="runs/bench_finetune_online")
    parser.add_argument("--override", nargs="*", default=[])
    parser.add_argument("--collect-only", action="store_true")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    root = Path(args.root)
    dirs = {a: root / f"{args.task}_{a}_seed{args.seed}" for a in args.algorithms}
    if not args.collect_only:
        pending = list(dirs.items())
        running: list[tuple[str, subprocess.Popen]] = []
        while pending or running:
            while pending and len(running) < args.jobs:
                name, run_dir = pending.pop(0)
                run_dir.parent.mkdir(parents=True, exist_ok=True)
                log = open(run_dir.parent / f"{run_dir.name}.log", "w")  # noqa: SIM115 (closed with the process)
                running.append((name, subprocess.Popen(run_one(name, args, run_dir), stdout=log, stderr=log)))
            name, proc = running.pop(0)
            if proc.wait() != 0:
                print(f"{name} failed (exit {proc.returncode}); see {dirs[name]}.log")
    readable = lambda d: (d / "eval.json").is_file() or (d / "checkpoints" / "latest.pt").is_file()  # noqa: E731
    results = {a: read_run(d) for a, d in dirs.items() if readable(d)}
    out = Path(args.out or f"benchmarks/results/finetune_online_{args.task}_seed{args.seed}.json")
    save_results(
        out,
        {
            "task": args.task,
            "checkpoint": str(args.checkpoint),
            "online_steps": args.steps,
            "budget_overrides": {a: CPU_BUDGET[a] + args.override for a in args.algorithms},
            "machine": machine_info("cpu"),
            "runs": results,
        },
    )
    plot(results, args.task, out.with_suffix(".png"))
    print(
        json.dumps(
            {
                a: {"start": r["start_validation"], "test": r["test"].get("success_once")}
                for a, r in results.items()
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
