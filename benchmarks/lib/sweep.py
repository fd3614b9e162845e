"""Running ``l1flow-rl train`` and ``l1flow-rl eval`` for benchmark grids, resumably.

Each run is a subprocess (one crash or a simulator fault ends that run, not the sweep) in its own
run directory under the sweep's root; a run whose ``eval.json`` exists is read, not repeated, and
an interrupted one resumes from its ``latest.pt``. Hand-written rather than hydra multirun because
a sweep here also re-scores finished networks under other samplers and must survive being stopped
and started again.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "Run",
    "convergence_steps",
    "headline_metric",
    "make_demos",
    "mean_and_spread",
    "plot_success_curves",
    "read_history",
    "rescore",
    "run_budget",
    "seed_record",
    "steps_to_fraction_of_best",
    "still_rising",
    "train",
    "train_side_by_side",
]


@dataclass
class Run:
    """One training run of a grid: its name, overrides and where it lives."""

    name: str
    overrides: list[str]
    run_dir: Path
    log: Path = field(init=False)

    def __post_init__(self) -> None:
        self.log = self.run_dir.with_suffix(".log")

    @property
    def done(self) -> bool:
        return (self.run_dir / "eval.json").is_file()


def _cli(args: Sequence[str], log: Path, env: dict[str, str] | None = None) -> int:
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as out:
        out.write("\n$ l1flow-rl " + " ".join(args) + "\n")
        out.flush()
        proc = subprocess.run(
            [sys.executable, "-m", "l1flow_rl.commands.cli", *args],
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, **(env or {})},
            check=False,
        )
    return proc.returncode


def config_mismatches(run: Run) -> list[str]:
    """The run's overrides that its saved ``config.yaml`` disagrees with (``task=X`` / ``policy=X``
    compare the group's ``name``): a finished run of another setting in the same folder."""
    import yaml
    from omegaconf import OmegaConf

    path = run.run_dir / "config.yaml"
    if not path.is_file():
        return []
    cfg = OmegaConf.load(path)
    found = []
    for override in run.overrides:
        if override.startswith(("+", "~")) or "=" not in override:
            continue
        key, raw = override.split("=", 1)
        dotted = f"{key}.name" if key in ("task", "policy") else key
        saved = OmegaConf.select(cfg, dotted, default=None)
        if OmegaConf.is_config(saved):
            saved = OmegaConf.to_container(saved, resolve=True)
        wanted = yaml.safe_load(raw)
        if saved != wanted:
            found.append(f"{key}: the folder's run has {saved!r}, this sweep asks for {wanted!r}")
    return found


def train(run: Run, data_dir: Path, threads: int | None = None) -> dict[str, Any]:
    """Train (or resume, or just read) ``run``; returns its final eval.json. ``threads``: torch's
    intra-op threads for the run (set when several runs share the machine). A finished run whose
    saved config disagrees with the run's overrides is an error, not a result."""
    if run.done and (mismatches := config_mismatches(run)):
        raise RuntimeError(
            f"{run.run_dir} holds a finished run of another setting:\n  "
            + "\n  ".join(mismatches)
            + "\nmove it away or give this sweep another --root"
        )
    if not run.done:
        resume = ["resume=true"] if (run.run_dir / "checkpoints" / "latest.pt").is_file() else []
        args = ["train", *run.overrides, f"run_dir={run.run_dir}", f"data_dir={data_dir}", *resume]
        code = _cli(args, run.log, {"OMP_NUM_THREADS": str(threads)} if threads else None)
        if code != 0:
            raise RuntimeError(f"{run.name}: l1flow-rl train exited with {code}; see {run.log}")
    return json.loads((run.run_dir / "eval.json").read_text())


def make_demos(overrides: Sequence[str], data_dir: Path, log: Path) -> None:
    """Make a task's demonstrations once, before runs that share them train side by side (two runs
    making the same file at once would race)."""
    code = _cli(["demos", *overrides, f"data_dir={data_dir}"], log)
    if code != 0:
        raise RuntimeError(f"l1flow-rl demos {' '.join(overrides)} exited with {code}; see {log}")


def train_side_by_side(runs: Sequence[Run], data_dir: Path, jobs: int) -> None:
    """Train the unfinished ``runs`` ``jobs`` at a time, cores/jobs torch threads each (small networks
    use several cores poorly). Make the runs' shared demonstrations first (``make_demos``): runs
    making the same file at once would race."""
    threads = _threads(jobs)
    _side_by_side([(train, (r, data_dir, threads)) for r in runs if not r.done], jobs, "run(s)")


def rescore(
    run: Run, name: str, overrides: Sequence[str], checkpoint: str | None = None, threads: int | None = None
) -> dict[str, Any]:
    """Evaluate the run's trained network under other settings (a sampler swap, another protocol);
    results go to ``<run_dir>/rescore_<name>/eval.json``.

    ``checkpoint`` (a file in the run's checkpoints/) defaults to ``best.pt``: the model the run's own
    test figures belong to (chosen on the validation seeds), so that a re-scoring differs from them in
    its settings only; ``latest.pt`` where no evaluation chose one. A saved re-scoring of another
    checkpoint is redone. ``threads``: torch's intra-op threads (set when several share the machine)."""
    ckpt_dir = run.run_dir / "checkpoints"
    if checkpoint is None:
        checkpoint = "best.pt" if (ckpt_dir / "best.pt").is_file() else "latest.pt"
    ckpt = ckpt_dir / checkpoint
    out = run.run_dir / f"rescore_{name}"
    saved = out / "eval.json"
    # a run's records copied without its network: read the saved re-scoring as it is
    restored = saved.is_file() and not ckpt.is_file()
    if (
        saved.is_file()
        and not restored
        and Path(json.loads(saved.read_text()).get("checkpoint", "")).name != checkpoint
    ):
        saved.unlink()  # made from another checkpoint (older sweeps re-scored latest.pt)
    if not saved.is_file() and not ckpt.is_file():
        raise FileNotFoundError(
            f"{run.name}: no {ckpt} to re-score ({name}); a run copied without its checkpoints has its "
            f"records only: remove {run.run_dir} to train it again"
        )
    if not saved.is_file():
        env = {"OMP_NUM_THREADS": str(threads)} if threads else None
        code = _cli(["eval", f"checkpoint={ckpt}", f"run_dir={out}", *overrides], run.log, env)
        if code != 0:
            raise RuntimeError(f"{run.name}: l1flow-rl eval ({name}) exited with {code}; see {run.log}")
    return json.loads((out / "eval.json").read_text())


def rescore_side_by_side(jobs: Sequence[tuple[Run, str, Sequence[str]]], workers: int) -> None:
    """Run the re-scorings ``(run, name, overrides)`` ``workers`` at a time (each is one process on
    cores/workers threads); the results land on disk, where ``rescore`` then reads them back."""
    threads = _threads(workers)
    calls = [(rescore, (run, name, overrides, None, threads)) for run, name, overrides in jobs]
    _side_by_side(calls, workers, "re-scoring(s)")


def _threads(workers: int) -> int:
    # the cores this process may use (taskset, cgroups), not the machine's: a sweep pinned to one core
    # gives its runs one thread each
    return max(1, len(os.sched_getaffinity(0)) // workers)


def _side_by_side(calls: Sequence[tuple[Any, tuple]], workers: int, what: str) -> None:
    """Run ``fn(*args)`` for every call, ``workers`` at a time (each starts its own process), and
    raise once all are done if any failed."""
    with ThreadPoolExecutor(workers) as pool:
        futures = [pool.submit(fn, *args) for fn, args in calls]
    failed = [f.exception() for f in futures if f.exception()]
    if failed:
        raise RuntimeError(f"{len(failed)} {what} failed: {failed[0]}")


def read_history(run: Run, split: str = "val") -> list[dict[str, Any]]:
    """The run's evaluations on one seed split (the validation curve by default), one per step, from
    ``history.json``."""
    path = run.run_dir / "history.json"
    if not path.is_file():
        return []
    by_step: dict[int, dict[str, Any]] = {}
    for e in json.loads(path.read_text()).get("evals", []):
        if e.get("split", split) == split:
            by_step.setdefault(int(e["step"]), e)
    return [by_step[s] for s in sorted(by_step)]


def steps_to_fraction_of_best(curve: Sequence[tuple[int, float]], fraction: float = 0.9) -> int | None:
    """The first step at which the curve reaches ``fraction`` of its best value (None: empty or 0)."""
    if not curve:
        return None
    best = max(v for _, v in curve)
    if best <= 0:
        return None
    return next(step for step, v in curve if v >= fraction * best)


def still_rising(curve: Sequence[tuple[int, float]], fraction: float = 0.9) -> bool:
    """Whether the curve first came within ``fraction`` of its best at its last validation: it had not
    flattened within the budget, so its steps-to-``fraction`` is a lower bound, not a measurement."""
    if len(curve) < 2:
        return False
    return steps_to_fraction_of_best(curve, fraction) == curve[-1][0]


def convergence_steps(block: dict[str, Any]) -> list[tuple[int, bool]]:
    """Per seed of a success file's method block: (steps to 90 % of its best, still rising at the end).

    Read from the saved curves where the block has them (files from before ``still_rising`` existed
    included), else from its steps-to-90 % figures, which cannot say whether a curve was still rising."""
    curves = [[(int(s), float(v)) for s, v in c] for c in block.get("curves") or []]
    if curves:
        steps = [(steps_to_fraction_of_best(c), still_rising(c)) for c in curves]
    else:
        steps = [(s, False) for s in block.get("steps_to_90pct_of_best") or []]
    return [(s, rising) for s, rising in steps if s]


#: the success curves' colour of each method (matplotlib's default cycle)
METHOD_COLORS = {"l1flow": "C0", "flow": "C1", "ddpm": "C2", "regression": "C3"}


def plot_success_curves(results: dict[str, dict[str, Any]], path: Path, columns: int = 3) -> None:
    """Success against training step, one panel per task (the paper's Figure 4 style): each method's
    mean over seeds with its min-max band, from a success file's ``tasks`` blocks; ``columns``
    panels a row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(results)
    ncols = min(columns, len(tasks))
    nrows = -(-len(tasks) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.5 * ncols, 3.6 * nrows), squeeze=False)
    for ax, task in zip(axes.flat, tasks):
        for method, block in results[task].items():
            curves = [c for c in block["curves"] if c]
            if not curves:
                continue
            steps = sorted({s for c in curves for s, _ in c})
            values = [[v for c in curves if (v := dict(c).get(s)) is not None] for s in steps]
            mean = [sum(vs) / len(vs) for vs in values]
            lo, hi = [min(vs) for vs in values], [max(vs) for vs in values]
            # one colour per method in every panel and figure
            color = METHOD_COLORS.get(method, f"C{len(METHOD_COLORS) + sum(map(ord, method)) % 6}")
            label = method + (f" (validation: {v})" if (v := block.get("validation_sampler")) else "")
            ax.plot(steps, mean, "o-", ms=3, label=label, color=color)
            ax.fill_between(steps, lo, hi, color=color, alpha=0.15)
        ax.set_title(task, fontsize=9)
        ax.set_xlabel("training step")
        metric = next((b["metric"] for b in results[task].values()), "success_once")
        ax.set_ylabel(f"{metric} (validation seeds)")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(tasks) :]:
        ax.set_visible(False)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def mean_and_spread(values: Sequence[float]) -> dict[str, float]:
    """Mean, sample standard deviation, min and max over seeds."""
    n = len(values)
    if n == 0:
        return {"mean": math.nan, "std": math.nan, "min": math.nan, "max": math.nan, "n": 0}
    mean = sum(values) / n
    var = sum((v - mean) ** 2 for v in values) / (n - 1) if n > 1 else 0.0
    return {"mean": mean, "std": math.sqrt(var), "min": min(values), "max": max(values), "n": n}


def run_budget(run: Run) -> dict[str, Any]:
    """What a finished run cost, from its summary.json: steps, wall and CPU seconds summed over the
    invocations that resumed it. ``seconds_since_step`` > 0: resumed from a checkpoint older than
    those totals, so the seconds count from that step only (summaries written before the field
    existed lack it and counted their last invocation only). ``cpu_seconds_scope`` "process tree": the
    CPU seconds include simulator workers; without it they missed forkserver-started workers.
    ``machine``: CPU model, torch threads and load as the run ended (None before runs recorded it)."""
    path = run.run_dir / "summary.json"
    summary = json.loads(path.read_text()) if path.is_file() else {}
    keys = ("steps", "wall_seconds", "cpu_seconds", "seconds_since_step", "cpu_seconds_scope", "machine")
    return {k: summary.get(k) for k in keys}


def headline_metric(result: dict[str, Any]) -> str:
    """The metric an eval.json's protocol reports first (PushT: ``score``; else ``success_once``)."""
    return result.get("headline", {}).get("metric") or "success_once"


def seed_record(result: dict[str, Any]) -> dict[str, Any]:
    """What a results table keeps of one eval.json: success and the protocol's headline metric, their
    95 % intervals, the seed split."""
    metric = headline_metric(result)
    return {
        "success_once": result["success_once"],
        "ci95": result.get("ci95", {}).get("success_once"),
        "metric": metric,
        "value": result[metric],
        "value_ci95": result.get("ci95", {}).get(metric),
        "episodes": result.get("episodes"),
        "split": result.get("split"),
        "nfe_per_chunk": result.get("nfe_per_chunk"),
    }
