"""The paper's second table: L1 Flow against the distillation-based fast policies, collected from a
distillation grid and timed at batch 1 in one run.

The rows are the paper's: Diffusion Policy under DDPM (100 NFE), DDIM (10 and 1) and EDM (35, 19
and 1), Consistency Policy (3 and 1), OneDP-D and OneDP-S from each teacher (1), and L1 Flow (2).
The teachers, the students and the re-scorings are one grid's folder (``configs/grid/distillation_*``,
whose header gives the commands); L1 Flow's runs are the MLP success grid's of the same task, data,
network and budget::

    python -m benchmarks.success.bench_distillation runs/grid/distillation_can runs/grid/success_robosuite_mlp

Saved: ``benchmarks/results/distillation_<task>.json``. Per row: its method and NFE, the test of the
weights each seed ships (``bench_success``'s block: success_once with Wilson's interval per seed, the
validation curve, steps to 90 % of its best), the training steps each seed's weights went through
counting its teacher's (the paper counts a student's epochs with its teacher's), steps to 90 % of the
best counting the teacher's too, and the chunk latency at batch 1 on this machine's CPU: the seed-0
checkpoint under the row's sampler, every row in turn each round (one torch thread), as a multiple of
L1 Flow's in the same run. Time it on an idle machine: beside two busy jobs, DDPM-100's multiple of
L1 Flow's came out three times the idle one (long calls are preempted more). A grid with an
unfinished row is refused (exit 2, listing each) unless ``--partial``; a row with no finished run is
left out and named.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict

from benchmarks.lib.common import (
    RESULTS_DIR,
    format_table,
    interleaved,
    machine_info,
    parse_args,
    provenance,
    save_results,
)
from benchmarks.lib.runs import Run, grid_provenance, grid_runs
from benchmarks.success.bench_success import collect, finished_enough, grid_setting
from l1flow_rl.evaluation.evaluator import sampler_record
from l1flow_rl.workspace.checkpoint import load_actor

__all__ = ["ROWS", "Row", "main", "row_latency_calls"]


@dataclass(frozen=True)
class Row:
    """One row of the table: the label ``bench_success`` gives its evaluations (``<policy>`` or
    ``<policy>_<re-scoring>``) and the paper's name for it."""

    label: str
    method: str


#: the paper's table, in its order
ROWS = (
    Row("ddpm", "DP (DDPM)"),
    Row("ddpm_ddim10", "DP (DDIM)"),
    Row("ddpm_ddim1", "DP (DDIM)"),
    Row("edm", "DP (EDM)"),
    Row("edm_edm10", "DP (EDM)"),
    Row("edm_edm1", "DP (EDM)"),
    Row("consistency_cp3", "Consistency Policy"),
    Row("consistency", "Consistency Policy"),
    Row("onedp_d", "OneDP-D (EDM teacher)"),
    Row("onedp_s", "OneDP-S (EDM teacher)"),
    Row("onedp_d_ddpm", "OneDP-D (DDPM teacher)"),
    Row("onedp_s_ddpm", "OneDP-S (DDPM teacher)"),
    Row("l1flow", "L1 Flow"),
)
#: the row every latency is a multiple of
REFERENCE = "l1flow"
#: the methods whose runs the table reads (a row's label begins with one of them)
POLICIES = ("ddpm", "edm", "consistency", "onedp_d", "onedp_s", "onedp_d_ddpm", "onedp_s_ddpm", "l1flow")


def _evaluation(run: Run, label: str) -> dict[str, Any]:
    """The eval.json behind ``label`` for one run: its own test, or the re-scoring the label names."""
    policy = run.setting("policy.name")
    if label == policy:
        return run.result()
    return json.loads(run.rescorings()[label.removeprefix(policy + "_")].read_text())


def _scored_runs(label: str, by_policy: dict[str, list[Run]]) -> list[Run]:
    """The finished runs with an evaluation under ``label``, by seed: the runs of the longest policy
    name the label starts with, which were tested (the label is the policy's) or re-scored so."""
    policy = max((p for p in by_policy if label == p or label.startswith(p + "_")), key=len)
    rescoring = label.removeprefix(policy + "_")
    runs = [r for r in by_policy[policy] if r.done and (label == policy or rescoring in r.rescorings())]
    return sorted(runs, key=lambda r: r.setting("seed", 0))


def row_latency_calls(
    runs_by_label: dict[str, Run], batch: int = 1
) -> tuple[dict[str, Callable[[], None]], dict[str, int]]:
    """One call per row (an action chunk from a random observation, through the row's seed-0 actor
    under the sampler its evaluation recorded) and each row's NFE."""
    calls, nfe = {}, {}
    for label, run in runs_by_label.items():
        record = _evaluation(run, label)["sampler"]
        actor, _ = load_actor(run.run_dir / "checkpoints" / "best.pt")
        own = sampler_record(actor)
        if (record["name"], record["kwargs"]) != (own["name"], own["kwargs"]):
            actor = actor.with_sampler(record["name"], **record["kwargs"])
        policy, key = actor.policy, actor.in_keys[0]
        shapes, horizon = policy.encoder.obs_shapes, policy.obs_horizon
        entries = {k: torch.randn(batch, horizon, *shape) for k, shape in shapes.items()}
        obs = TensorDict({key: TensorDict(entries, [batch, horizon])}, [batch])

        @torch.inference_mode()
        def call(actor=actor, obs=obs) -> None:
            actor(obs.clone())

        calls[label], nfe[label] = call, int(record["nfe"])
    return calls, nfe


def _teacher_steps(evaluation: dict[str, Any]) -> int:
    """The training its teacher had when it taught (0: a run trained from demonstrations alone)."""
    return sum(s["steps"] for s in evaluation.get("ledger") or [] if s["stage"] == "teacher")


def _tested_steps(evaluation: dict[str, Any]) -> int:
    """Every stage the tested weights went through: a training run's test scores the step its
    validation chose (``selection``), which may precede its last; a re-scoring reads its checkpoint's
    ledger."""
    if "selection" in evaluation:
        return _teacher_steps(evaluation) + int(evaluation["selection"]["step"])
    return int(evaluation.get("total_steps_with_teacher") or evaluation["step"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("grids", nargs="+", help="the distillation grid's folder, then L1 Flow's grid")
    parser.add_argument("--partial", action="store_true", help="write what is finished; list what is not")
    parser.add_argument("--rounds", type=int, default=30, help="timed rounds of every row at batch 1")
    parser.add_argument("--out-dir", default=str(RESULTS_DIR), help="where distillation_<task>.json goes")
    args = parse_args(parser, argv)
    torch.set_num_threads(1)
    roots = [Path(g).as_posix() for g in args.grids]
    by_grid = [grid_runs(g) for g in args.grids]  # each folder walked once
    runs = [r for found in by_grid for r in found if r.setting("policy.name") in POLICIES]
    tasks = sorted({r.setting("task.name") for r in by_grid[0]})
    if len(tasks) != 1:
        print(f"{roots[0]}: expected the runs of one task, found {tasks or 'none'}", file=sys.stderr)
        return 2
    task = tasks[0]
    runs = [r for r in runs if r.setting("task.name") == task]
    by_policy: dict[str, list[Run]] = {}
    for r in runs:
        by_policy.setdefault(r.setting("policy.name"), []).append(r)
    networks = sorted({str(r.setting("network.name")) for r in runs})
    if len(networks) != 1:
        print(f"{task}: the rows ran on different networks ({', '.join(networks)})", file=sys.stderr)
        return 2
    if not finished_enough({task: by_policy}, args.partial):
        return 2
    blocks = collect(runs).get(task, {})
    missing = [row.label for row in ROWS if row.label not in blocks]
    if missing and not args.partial:
        print(f"{task}: no finished evaluation for {', '.join(missing)}", file=sys.stderr)
        return 2
    rows = [row for row in ROWS if row.label in blocks]
    scored = {row.label: _scored_runs(row.label, by_policy) for row in rows}
    calls, nfe = row_latency_calls({label: runs[0] for label, runs in scored.items()})
    times = interleaved(calls, args.rounds, torch.device("cpu"))
    reference = times.get(REFERENCE)
    table: dict[str, Any] = {}
    for row in rows:
        block = blocks[row.label]
        evaluations = [_evaluation(r, row.label) for r in scored[row.label]]
        teacher = [_teacher_steps(e) for e in evaluations]  # per seed, as the block's
        to_90 = block["steps_to_90pct_of_best"]  # per seed; empty for a re-scoring (no curve)
        table[row.label] = {
            "method": row.method,
            "nfe": nfe[row.label],
            **block,
            # every stage the shipped weights went through, the teacher's to its checkpoint included
            "training_steps": [_tested_steps(e) for e in evaluations],
            "teacher_steps": teacher,
            # each seed's own curve shifted by its teacher's steps (None: its validation never rose
            # above 0; empty: a re-scoring's row)
            "steps_to_90pct_of_best_with_teacher": [
                t + s if s is not None else None for t, s in zip(teacher, to_90, strict=True)
            ]
            if to_90
            else [],
            "latency_batch1_ms": {k: round(v, 3) for k, v in times[row.label].items()},
            "latency_vs_l1flow": round(times[row.label]["wall_ms"] / reference["wall_ms"], 2)
            if reference
            else None,
        }
    figures = {
        "machine": machine_info(),
        "quick": False,
        "args": {**grid_setting(task, runs, roots), "network": networks[0], "latency_rounds": args.rounds},
        "task": task,
        "missing_rows": missing,
        "rows": table,
        "provenance": {**(provenance() or {}), "runs": grid_provenance(roots, runs)},
    }
    out = save_results(Path(args.out_dir) / f"distillation_{task}.json", figures)
    print(
        format_table(
            [
                {
                    "row": f"{r['method']} {r['nfe']}",
                    "success_once": r["success_once"]["mean"],
                    "seeds": r["success_once"]["n"],
                    "training steps": max(r["training_steps"]),
                    "batch-1 ms": r["latency_batch1_ms"]["wall_ms"],
                }
                for r in table.values()
            ],
            ["row", "success_once", "seeds", "training steps", "batch-1 ms"],
        )
    )
    if missing:
        print(f"left out (not finished): {', '.join(missing)}", file=sys.stderr)
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
