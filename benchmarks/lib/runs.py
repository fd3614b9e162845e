"""Reading finished runs back: a grid's folder (``l1flow-rl train -m +grid=NAME``, ``configs/grid/``),
each run's test figures, validation curve, budget and re-scorings, and what the grid ran on.

A grid's folder is hydra's sweep directory: one folder per job, holding hydra's record (``.hydra/``)
and the run's own files (``config.yaml``, ``eval.json``, ``history.json``, ``summary.json``,
``checkpoints/``); an ``l1flow-rl eval -m`` re-scoring (``configs/rescore/``) puts each evaluation in
``<run>/rescore_<name>/``. The scripts that turn a grid into a results file
(``benchmarks.success.bench_success``, ``bench_ablations``) read it through this module.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

from l1flow_rl.workspace.checkpoint import flatten_config

__all__ = [
    "Run",
    "grid_provenance",
    "grid_runs",
    "headline_metric",
    "read_history",
    "run_budget",
    "seed_record",
]


@dataclass
class Run:
    """One training run: its name, the overrides it ran with and its folder."""

    name: str
    overrides: list[str]
    run_dir: Path
    log: Path = field(init=False)

    def __post_init__(self) -> None:
        self.run_dir = Path(self.run_dir)
        self.log = self.run_dir.with_suffix(".log")

    @property
    def done(self) -> bool:
        """Whether its test figures exist (``eval.json``)."""
        return (self.run_dir / "eval.json").is_file()

    def result(self) -> dict[str, Any]:
        """Its test figures (``eval.json``)."""
        return json.loads((self.run_dir / "eval.json").read_text())

    @cached_property
    def config(self) -> dict[str, Any]:
        """The config it ran with (its ``config.yaml``, resolved), empty when missing."""
        from omegaconf import OmegaConf

        path = self.run_dir / "config.yaml"
        if not path.is_file():
            return {}
        return OmegaConf.to_container(OmegaConf.load(path), resolve=False)  # type: ignore[return-value]

    def setting(self, dotted: str, default: Any = None) -> Any:
        """One field of :attr:`config` (``"task.name"``)."""
        node: Any = self.config
        for part in dotted.split("."):
            if not isinstance(node, dict) or part not in node:
                return default
            node = node[part]
        return node

    def choice(self, group: str) -> str | None:
        """The option it chose in a config group (``policy`` -> ``onedp_d``), from hydra's record of
        the job; None when the record lacks it. A config may rename what it chose (``policy.name``)."""
        import yaml

        record = self.run_dir / ".hydra" / "hydra.yaml"
        if not record.is_file():
            return None
        runtime = (yaml.safe_load(record.read_text()) or {}).get("hydra", {}).get("runtime", {})
        return (runtime.get("choices") or {}).get(group)

    def rescorings(self) -> dict[str, Path]:
        """Its finished re-scorings by name: ``rescore_<name>/eval.json`` (``l1flow-rl eval -m``)."""
        return {
            p.parent.name.removeprefix("rescore_"): p
            for p in sorted(self.run_dir.glob("rescore_*/eval.json"))
        }


def _job_record(folder: Path) -> tuple[str | None, int, list[str]]:
    """(command, job number, overrides) of a hydra job's folder, from its ``.hydra/`` record."""
    import yaml

    hydra_file, overrides_file = folder / ".hydra" / "hydra.yaml", folder / ".hydra" / "overrides.yaml"
    job = (yaml.safe_load(hydra_file.read_text()) or {}).get("hydra", {}).get("job", {})
    overrides = yaml.safe_load(overrides_file.read_text()) if overrides_file.is_file() else []
    return job.get("name"), int(job.get("num") or 0), [str(o) for o in overrides or []]


def grid_runs(root: str | Path) -> list[Run]:
    """Every training job of the grid whose folder is ``root`` (hydra's ``hydra.sweep.dir``), in the
    order the grid launched them; named by their folder under ``root``. Evaluation jobs (re-scorings)
    are not runs: :meth:`Run.rescorings` reads them."""
    root = Path(root)
    found = []
    for record in root.rglob(".hydra/hydra.yaml"):
        folder = record.parent.parent
        command, num, overrides = _job_record(folder)
        if command == "train":
            name = folder.relative_to(root).as_posix()
            found.append((num, name, Run(name, overrides, folder)))
    return [run for _, _, run in sorted(found, key=lambda t: (t[0], t[1]))]


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


def _unflatten(flat: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for dotted, value in flat.items():
        node = out
        *parents, leaf = dotted.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return out


def grid_provenance(roots: Iterable[str | Path], runs: list[Run]) -> dict[str, Any]:
    """What a results file records of the runs behind it (``provenance.runs``): the grid folders,
    the grid's command (the overrides all its jobs share), the commits the runs and their
    re-scorings were measured at (``benchmarks.report`` dates the file by them), their launchers,
    when the first and last were measured, how many evaluations record no commit, the config every
    run shares (resolved) and the values of the fields they differ in (``swept``)."""
    records = []
    for run in runs:
        for path in [run.run_dir / "eval.json", *run.rescorings().values()]:
            if path.is_file():
                records.append(json.loads(path.read_text()).get("provenance") or {})
    commits = sorted({c for r in records for c in r.get("commits") or []})
    launchers = sorted({r["launcher"] for r in records if r.get("launcher")})
    times = sorted(r["measured_at"] for r in records if r.get("measured_at"))
    flat = [flatten_config(run.config) for run in runs if run.config]
    keys = sorted({k for f in flat for k in f})
    ignored = ("run_dir", "data_dir", "resume")
    shared, swept = {}, {}
    for key in keys:
        if key in ignored:
            continue
        values = [f.get(key) for f in flat]
        distinct = sorted({json.dumps(v, sort_keys=True) for v in values})
        if len(distinct) == 1:
            shared[key] = values[0]
        else:
            swept[key] = [json.loads(v) for v in distinct]
    # the grid's command: the overrides every job shares (its +grid=..., not the values it swept)
    shared_overrides = [o for o in (runs[0].overrides if runs else []) if all(o in r.overrides for r in runs)]
    return {
        "grids": [Path(r).as_posix() for r in roots],
        "command": " ".join(["l1flow-rl train -m", *shared_overrides]) if shared_overrides else None,
        "commits": commits,
        "launchers": launchers,
        "measured": [times[0], times[-1]] if times else None,
        "evaluations": len(records),
        # evaluations whose commit is unknown (run before runs recorded it): the file cannot be
        # proven fresh
        "without_commit": sum(not r.get("commits") for r in records),
        "config": _unflatten(shared),
        "swept": swept,
    }
