"""Fine-tuning at a glance: the headline arms of every fine-tuning start, one table and one figure per
start, read from the saved ``finetune_online_*.json`` files.

Each ``bench_finetune_online`` invocation saves one file per experiment (one recipe, its controls); a
reader asking "what helped on Can" wants the arms from one start side by side. :data:`HEADLINE` names
them (a curated list: which rows a reader needs is a judgement, the numbers are not), and
``benchmarks.report`` renders the table in RESULTS.md's summary and between the README's fine-tuning
markers, and draws ``finetune_overview_<start>.png`` per start: each online arm's validation curve
(mean and min-max band over seeds) against env steps, each arm's test as a marker (online and data
arms, at their env steps) or a dashed line (arms that take no env step), the start's test as a grey line.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks.lib.stats import runs_aggregate

__all__ = ["HEADLINE", "Arm", "arm_name", "arms_table", "figure_paths", "overview_figures", "overview_table"]


@dataclass(frozen=True)
class Arm:
    """One row: ``key`` is ``algorithms.<name>`` (an online arm) or ``controls.<name>`` (an arm without
    env steps of its own: continued BC, a TD-only arm, or a data method whose env steps are its
    ``data_cost``) of results file ``file``; ``baseline`` the (file, key) of the continued-BC control it
    is measured against, if any; ``more`` further files of the same command run for other seeds (an
    online arm): their runs join this arm's, checked to share its start and settings."""

    label: str
    file: str
    key: str
    baseline: tuple[str, str] | None = None
    more: tuple[str, ...] = ()

    @property
    def files(self) -> tuple[str, ...]:
        return (self.file, *self.more)

    @property
    def online(self) -> bool:
        return self.key.startswith("algorithms.")


_CAN_C = "finetune_online_robosuite_can_mixed30c_"
_CAN_CBC = (f"{_CAN_C}continued_bc.json", "controls.continued_bc")
_PICK = "finetune_online_maniskill_pickcube_mixed50b_filtered_bc_an0p02_mask_100k.json"
_SQUARE_CBC = ("finetune_online_robosuite_square50_continued_bc_8k.json", "controls.continued_bc")

_PICK_MLP = "finetune_online_maniskill_pickcube_mlp_mixed50"
_PICK_MLP_CBC = (f"{_PICK_MLP}.json", "controls.continued_bc")
_CAN_MLP = "finetune_online_robosuite_can_mlp_mixed30"
_CAN_MLP_CBC = (f"{_CAN_MLP}.json", "controls.continued_bc")
_CAN_MLP_R = f"{_CAN_MLP}_remade"
_CAN_MLP_R_CBC = (f"{_CAN_MLP_R}.json", "controls.continued_bc")
_SQUARE_MLP = "finetune_online_robosuite_square50_mlp"
_SQUARE_MLP_CBC = (f"{_SQUARE_MLP}.json", "controls.continued_bc")

#: start -> its arms. Every arm of a start must share the start's run and test figure (checked): rows
#: from different starts are not comparable. The critic arms' starts are the ones they were measured on.
HEADLINE: dict[str, list[Arm]] = {
    "PickCube (50 mixed episodes)": [
        Arm(
            "filtered BC online, preset `filtered_bc_delta`",
            _PICK,
            "algorithms.filtered_bc",
            (_PICK, "controls.continued_bc"),
        ),
        Arm("continued BC, 8,000 updates", _PICK, "controls.continued_bc"),
    ],
    "PickCube (50 mixed episodes, MLP start)": [
        Arm(
            "filtered BC online, preset `filtered_bc_delta`",
            f"{_PICK_MLP}.json",
            "algorithms.filtered_bc_delta",
            _PICK_MLP_CBC,
        ),
        Arm("continued BC, 8,000 updates", *_PICK_MLP_CBC),
        Arm(
            "flow-Q online, preset `flowq` (10,000 critic-only offline updates)",
            f"{_PICK_MLP}_flowq_critic_only.json",
            "algorithms.flowq",
            _PICK_MLP_CBC,
        ),
    ],
    "Can (30 mixed episodes)": [
        Arm(
            "filtered BC online, preset `filtered_bc`",
            f"{_CAN_C}filtered_bc_ema.json",
            "algorithms.filtered_bc",
            _CAN_CBC,
        ),
        Arm("continued BC, 4,000 updates", *_CAN_CBC),
        Arm(
            "200 shifted replays, then 4,000 continued filtered-BC updates",
            f"{_CAN_C}shift200.json",
            "controls.continued_bc",
            _CAN_CBC,
        ),
        Arm(
            "200 shifted replays, then filtered BC online",
            f"{_CAN_C}shift200_online.json",
            "algorithms.filtered_bc",
        ),
        Arm("QC, flow frozen, best of 8, online", f"{_CAN_C}qc_frozen_100k.json", "algorithms.qc", _CAN_CBC),
        Arm(
            "QC's TD-only arm, 11,540 updates",
            f"{_CAN_C}qc_frozen_100k.json",
            "controls.qc_offline",
            _CAN_CBC,
        ),
        Arm("FQL online (3,000 offline updates first)", f"{_CAN_C}fql_50k.json", "algorithms.fql"),
        Arm("FQL's TD-only arm, 5,240 updates", f"{_CAN_C}fql_50k.json", "controls.fql_offline"),
    ],
    "Can (30 mixed episodes, MLP start)": [
        Arm(
            "filtered BC online, preset `filtered_bc`",
            f"{_CAN_MLP}.json",
            "algorithms.filtered_bc",
            _CAN_MLP_CBC,
        ),
        Arm("continued BC, 8,000 updates", *_CAN_MLP_CBC),
        Arm(
            "flow-Q online, preset `flowq` (10,000 critic-only offline updates)",
            f"{_CAN_MLP}_flowq.json",
            "algorithms.flowq",
            _CAN_MLP_CBC,
            more=(f"{_CAN_MLP}_flowq_seed1.json",),
        ),
        Arm(
            "flow-Q online, critics 2 x 256, 1 update per env step (the preset's: 0.5)",
            f"{_CAN_MLP}_flowq_critic2x256_utd1.json",
            "algorithms.flowq",
            _CAN_MLP_CBC,
        ),
    ],
    "Can (30 mixed episodes, MLP start remade)": [
        Arm(
            "filtered BC online, preset `filtered_bc`",
            f"{_CAN_MLP_R}.json",
            "algorithms.filtered_bc",
            _CAN_MLP_R_CBC,
        ),
        Arm("continued BC, 8,000 updates", *_CAN_MLP_R_CBC),
        Arm(
            "flow-Q online, preset `flowq` (10,000 critic-only offline updates)",
            f"{_CAN_MLP_R}_flowq.json",
            "algorithms.flowq",
            _CAN_MLP_R_CBC,
        ),
        Arm("flow-Q's TD-only arm, 57,500 updates", f"{_CAN_MLP_R}_flowq.json", "controls.flowq_offline"),
        Arm(
            "flow-Q online, critics 2 x 256 (the preset's: 4 x 512)",
            f"{_CAN_MLP_R}_flowq_critic2x256.json",
            "algorithms.flowq",
            _CAN_MLP_R_CBC,
        ),
        Arm(
            "flow-Q online, critics 2 x 256, 1 update per env step (the preset's: 0.5)",
            f"{_CAN_MLP_R}_flowq_critic2x256_utd1.json",
            "algorithms.flowq",
            _CAN_MLP_R_CBC,
        ),
        Arm("QC online, best of 8", f"{_CAN_MLP_R}_qc8.json", "algorithms.qc", _CAN_MLP_R_CBC),
    ],
    "Square (50 scripted episodes)": [
        Arm(
            "200 shifted replays, then 8,000 continued filtered-BC updates",
            "finetune_online_robosuite_square50_shift200_8k.json",
            "controls.continued_bc",
            _SQUARE_CBC,
        ),
        Arm("continued BC, 8,000 updates", *_SQUARE_CBC),
    ],
    "Square (50 scripted episodes, MLP start)": [
        Arm(
            "filtered BC online, preset `filtered_bc`",
            f"{_SQUARE_MLP}.json",
            "algorithms.filtered_bc",
            _SQUARE_MLP_CBC,
        ),
        Arm("continued BC, 8,000 updates", *_SQUARE_MLP_CBC),
        Arm(
            "flow-Q online, preset `flowq` (10,000 critic-only offline updates)",
            f"{_SQUARE_MLP}_flowq.json",
            "algorithms.flowq",
            _SQUARE_MLP_CBC,
        ),
    ],
}


def _block(data: dict, key: str, file: str) -> dict:
    group, _, name = key.partition(".")
    block = data.get(group, {}).get(name)
    if block is None:
        raise KeyError(f"{file}: no {key!r} (it has {sorted(data.get(group, {}))}); fix HEADLINE")
    return block


def _start_of(data: dict) -> tuple[str, float]:
    start = data["controls"]["bc_start"]
    return start["run_dir"], start["test"]["success_once"]


def _pooled(arm: Arm, load: Callable[[str], dict]) -> tuple[dict, dict | None]:
    """``arm``'s block with the runs of every file it names (one file: as saved), and its last weights'
    control (``<name>_last``; joined: its seeds alone, whose tests the tables read; None unless every
    file has one)."""
    data = load(arm.file)
    block = _block(data, arm.key, arm.file)
    group, _, name = arm.key.partition(".")
    lasts = [data.get("controls", {}).get(f"{name}_last")]
    if not arm.more:
        return block, lasts[0]
    if group != "algorithms":
        raise ValueError(f"{arm.label!r}: only an online arm joins the runs of several files")
    runs = dict(block["runs"])
    for other_name in arm.more:
        other = load(other_name)
        more = _block(other, arm.key, other_name)
        if _start_of(other) != _start_of(data):
            raise ValueError(
                f"{other_name} starts from {_start_of(other)}, {arm.file} from {_start_of(data)}: "
                f"the files of arm {arm.label!r} must share its start"
            )
        if more.get("budget_overrides") != block.get("budget_overrides"):
            raise ValueError(
                f"{other_name}: {arm.key} ran with {more.get('budget_overrides')}, in {arm.file} with "
                f"{block.get('budget_overrides')}: the files of arm {arm.label!r} must share its settings"
            )
        if twice := sorted(set(runs) & set(more["runs"])):
            raise ValueError(f"{other_name}: seed {', '.join(twice)} of {arm.key} is also in an earlier file")
        runs.update(more["runs"])
        lasts.append(other.get("controls", {}).get(f"{name}_last"))
    pooled = {**block, "runs": runs, "aggregate": runs_aggregate({int(s): r for s, r in runs.items()})}
    if any(last is None for last in lasts):
        return pooled, None
    return pooled, {"seeds": {s: r for last in lasts for s, r in last["seeds"].items()}}


def _tests(block: dict, online: bool) -> list[float]:
    """The seeds' test success_once, in seed order."""
    if online:
        runs = sorted(block["runs"].items())
        return [
            r["test"]["success_once"]
            for _, r in runs
            if (r.get("test") or {}).get("success_once") is not None
        ]
    seeds = block.get("seeds") or {}
    return [s["test"]["success_once"] for _, s in sorted(seeds.items())] or [block["test"]["success_once"]]


def _data_steps(block: dict) -> float | None:
    """A data arm's env steps: the mean over seeds of what its replays cost."""
    costs = [s["data_cost"]["env_steps"] for s in (block.get("seeds") or {}).values() if s.get("data_cost")]
    return sum(costs) / len(costs) if costs else None


def _load(results: Path, name: str, cache: dict[str, dict], label: str) -> dict:
    if name not in cache:
        path = results / name
        if not path.is_file():
            raise FileNotFoundError(f"{path}: named by HEADLINE ({label!r}) but not saved")
        cache[name] = json.loads(path.read_text())
    return cache[name]


def _read(results: Path, arm: Arm, cache: dict[str, dict]) -> dict[str, Any]:
    data = _load(results, arm.file, cache, arm.label)
    block, _ = _pooled(arm, lambda name: _load(results, name, cache, arm.label))
    tests = _tests(block, arm.online)
    curve = block.get("aggregate", {}).get("curve", []) if arm.online else []
    row = {
        "arm": arm,
        "start": data["controls"]["bc_start"],
        "tests": tests,
        "mean": sum(tests) / len(tests),
        "curve": curve,
        "env_steps": max((c["env_steps"] for c in curve), default=0) if arm.online else _data_steps(block),
    }
    if arm.baseline:
        name, key = arm.baseline
        base = _tests(_block(_load(results, name, cache, arm.label), key, name), False)
        row["baseline"] = sum(base) / len(base)
    return row


def _rows(results: Path, headline: dict[str, list[Arm]]) -> dict[str, list[dict[str, Any]]]:
    """Each start's rows, after checking that every arm of a start starts where its first does."""
    cache: dict[str, dict] = {}
    out = {}
    for start, arms in headline.items():
        rows = [_read(results, a, cache) for a in arms]
        first = rows[0]["start"]
        for r in rows[1:]:
            if (r["start"]["run_dir"], r["start"]["test"]["success_once"]) != (
                first["run_dir"],
                first["test"]["success_once"],
            ):
                raise ValueError(
                    f"HEADLINE[{start!r}]: {r['arm'].file} starts from {r['start']['run_dir']} (test "
                    f"{r['start']['test']['success_once']}), {rows[0]['arm'].file} from {first['run_dir']} "
                    f"(test {first['test']['success_once']}): rows of one start must share it"
                )
        out[start] = rows
    return out


def _name(file: str) -> str:
    return file.removeprefix("finetune_online_").removesuffix(".json")


def _k(steps: float) -> str:
    return f"{steps / 1000:.3g}k"


def _points(diff: float) -> str:
    return f"{round(100 * diff):+d}"


def _any_saved(results: Path, headline: dict[str, list[Arm]]) -> bool:
    """Whether any file the headline names is saved (none: a fresh results folder)."""
    return any((results / f).is_file() for arms in headline.values() for a in arms for f in a.files)


def overview_table(results: Path, headline: dict[str, list[Arm]] = HEADLINE) -> str | None:
    """The markdown table of :data:`HEADLINE`, or None when none of its files is saved (a fresh folder).
    Each row names its file by a number, listed under the table."""
    if not _any_saved(results, headline):
        return None
    lines = [
        "| start (its test) | arm | seeds | env steps | test success (per seed) | over the start "
        "| over continued BC | file |",
        "|---|---|---|---|---|---|---|---|",
    ]
    files: list[str] = []
    for start, rows in _rows(results, headline).items():
        start_test = rows[0]["start"]["test"]["success_once"]
        for i, r in enumerate(rows):
            steps = r["env_steps"]
            if not r["arm"].online and steps is None:
                steps_text = "0"
            elif not r["arm"].online:
                steps_text = f"{_k(steps)} of replays"
            else:
                steps_text = _k(steps)
            files += [f for f in r["arm"].files if f not in files]
            first = f"{start} ({start_test:.2f})" if i == 0 else ""  # the start names its rows once
            lines.append(
                f"| {first} | {r['arm'].label} | {len(r['tests'])} | "
                f"{steps_text} | {r['mean']:.2f} ({' / '.join(f'{t:.2f}' for t in r['tests'])}) | "
                f"{_points(r['mean'] - start_test)} | "
                + (_points(r["mean"] - r["baseline"]) if "baseline" in r else "–")
                + f" | {', '.join(str(files.index(f) + 1) for f in r['arm'].files)} |"
            )
    note = (
        "Test: 100 episodes per seed on the test seeds, of the best-validated weights (a run keeps its "
        "start unless a model validates more than one standard error above it); differences in points of "
        "the mean over seeds. A data "
        "arm's env steps are those its replays took. Files (`finetune_online_<name>.json`): "
        + ", ".join(f"{i} `{_name(f)}`" for i, f in enumerate(files, 1))
        + "."
    )
    return "\n".join(lines) + "\n\n" + note


#: the algorithms' names as a reader writes them
_ALGORITHMS = {
    "filtered_bc": "filtered BC",
    "qc": "QC",
    "fql": "FQL",
    "dsrl": "DSRL",
    "dsrl_na": "DSRL-NA",
    "continued_bc": "continued BC",
}
#: an override's key -> how an arm's name says it (``{}``: the value)
_OVERRIDES = {
    "online.action_noise": "action noise {}",
    "finetune.filtered_bc.mask_padding": "padding masked",
    "online.updates_per_step": "{} updates per env step",
    "finetune.batch_size": "batch {}",
    "finetune.qc.num_samples": "best of {}",
    "finetune.qc.freeze_flow": "flow frozen",
    "offline.steps": "{} offline updates first",
    "finetune.dsrl.init_alpha": "SAC alpha {}",
    "finetune.ema_power": "EMA power {}",
}
#: switches whose "false" is a setting a reader must see (the presets' value is true)
_SWITCHES = {"offline.critic_only": ("critics alone offline", "actor trained offline too")}
_REPLAYS = "demos.shifted_replays"
#: overrides not phrased in the list: the replays lead the name; the validation cadence trains nothing
_UNNAMED = {_REPLAYS, "offline.eval_every"}


def _phrase(override: str) -> str | None:
    key, _, value = override.partition("=")
    if key in _SWITCHES:
        return _SWITCHES[key][value.lower() != "true"]
    if key in _UNNAMED or value.lower() == "false":
        return None
    text = _OVERRIDES.get(key)
    if text is None:
        return f"`{override}`"
    return text.format(f"{int(value):,}" if value.isdigit() else value)


def arm_name(group: str, name: str, block: dict, overrides: list[str] | None) -> str:
    """A readable name for arm ``name`` of a results file's ``group`` ("algorithms" or "controls"):
    the algorithm, how it ran (online, its TD-only arm, continued BC), its update count, which weights
    were tested, and the overrides it ran with, e.g. "filtered BC online, action noise 0.02, padding
    masked"."""
    base, last = name.removesuffix("_last"), name.endswith("_last")
    updates = block.get("updates")
    if group == "algorithms":
        text = f"{_ALGORITHMS.get(base, base)} online"
    elif base.endswith("_offline"):
        alg = base.removesuffix("_offline")
        text = f"{_ALGORITHMS.get(alg, alg)}'s TD-only arm"
    elif base.startswith("continued_bc"):
        text = "continued BC"
        suffix = base.removeprefix("continued_bc").strip("_")
        if suffix.endswith("k") and suffix[:-1].isdigit():  # continued_bc_8k: its update count
            updates = updates or 1000 * int(suffix[:-1])
        elif suffix:  # continued_bc_on_the_50: what it trained on
            text += f" ({suffix.replace('_', ' ')})"
    else:
        text = f"{_ALGORITHMS.get(base, base)} online"
    if updates:
        text += f", {updates:,} updates"
    if last:
        text += ", last weights tested"
    overrides = overrides or []
    text += "".join(f", {p}" for o in overrides if (p := _phrase(o)))
    replays = next((o.partition("=")[2] for o in overrides if o.startswith(_REPLAYS + "=")), None)
    return f"{replays} shifted replays, then {text}" if replays else text


def _start_names(files: list[tuple[Path, dict]], headline: dict[str, list[Arm]]) -> dict[tuple, str]:
    """(start run, its test) -> the start's name in :data:`HEADLINE`, for the starts whose files are here."""
    by_name = {path.name: data for path, data in files}
    names = {}
    for start, arms in headline.items():
        data = by_name.get(arms[0].file)
        if data is not None:
            s = data["controls"]["bc_start"]
            names.setdefault((s["run_dir"], s["test"]["success_once"]), start)
    return names


def _validation(block: dict) -> str:
    curve = block.get("aggregate", {}).get("curve", [])
    return ", ".join(f"{c['env_steps'] / 1000:.3g}k: {c['mean']:.2f}" for c in curve) or "–"


def arms_table(files: list[tuple[Path, dict]], headline: dict[str, list[Arm]] = HEADLINE) -> str:
    """Every arm of every ``finetune_online_*.json`` in one table, grouped by start: its readable name,
    seeds, env steps, test success per seed, the validation curve of online arms, the gain over the
    start, and the file it comes from (by number, listed under the table)."""
    names = _start_names(files, headline)
    by_name = {path.name: data for path, data in files}
    number = {path.name: i for i, (path, _) in enumerate(files, 1)}
    joins = [a for arms in headline.values() for a in arms if a.more and all(f in by_name for f in a.files)]
    joined = {(a.file, a.key): a for a in joins}
    folded = {(f, a.key) for a in joins for f in a.more}  # their runs are in the row of the file they join
    by_start: dict[tuple, list] = {}
    for i, (path, data) in enumerate(files, 1):
        key = _start_of(data)
        blocks = {**data.get("controls", {}), **data.get("algorithms", {})}
        for group in ("controls", "algorithms"):
            for name, block in data.get(group, {}).items():
                if name == "bc_start" or (name.endswith("_last") and name.removesuffix("_last") in blocks):
                    continue  # an arm's last weights are a figure of its own row
                if (path.name, f"{group}.{name}") in folded:
                    continue
                last = blocks.get(f"{name}_last")
                ref = str(i)
                if (arm := joined.get((path.name, f"{group}.{name}"))) is not None:
                    block, last = _pooled(arm, by_name.__getitem__)
                    ref = ", ".join(str(number[f]) for f in arm.files)
                online = group == "algorithms"
                tests = _tests(block, online)
                last_tests = _tests(last, False) if last is not None else []
                stopped = online and not tests and bool(block.get("aggregate", {}).get("curve"))
                if not tests and not stopped:  # an arm whose runs all lack a test, and a curve
                    continue
                if online:
                    overrides = block.get("budget_overrides")
                    steps = _k(max((c["env_steps"] for c in block["aggregate"]["curve"]), default=0))
                else:
                    overrides = block.get("overrides")
                    replayed = _data_steps(block)
                    steps = "0" if replayed is None else f"{_k(replayed)} of replays"
                row = [arm_name(group, name, block, overrides), len(tests), steps, tests, last_tests]
                by_start.setdefault(key, []).append((row, _validation(block) if online else "–", ref))
    lines = [
        "| start (its test) | arm | seeds | env steps | test success (per seed) | validation (mean) at env "
        "steps | over the start | file |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (run, start_test), rows in by_start.items():
        for j, ((arm, seeds, steps, tests, last_tests), curve, i) in enumerate(rows):
            first = f"{names.get((run, start_test), f'`{run}`')} ({start_test:.2f})" if j == 0 else ""
            if not tests:  # stopped before its test: its validation curve is the figure
                lines.append(f"| {first} | {arm} | stopped | {steps} | – | {curve} | – | {i} |")
                continue
            mean = sum(tests) / len(tests)
            per_seed = " / ".join(f"{t:.2f}" for t in tests)
            if last_tests:
                per_seed += f"; last weights {sum(last_tests) / len(last_tests):.2f}"
            lines.append(
                f"| {first} | {arm} | {seeds} | {steps} | {mean:.2f} ({per_seed}) "
                f"| {curve} | {_points(mean - start_test)} | {i} |"
            )
    note = (
        "Test: 100 episodes per seed on the test seeds, of the best-validated weights (after a semicolon: "
        "of the last weights, mean over seeds), or of the last ones where the arm says so; validation: 50 "
        "episodes, mean over seeds. An arm without env steps "
        "trains on the start's data only (its TD-only arm: the critic arms' updates without collecting)."
    )
    return "\n".join(lines) + "\n\n" + note


def _slug(start: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", start.lower()).strip("_")


def figure_paths(results: Path, headline: dict[str, list[Arm]] = HEADLINE) -> list[Path]:
    """Where :func:`overview_figures` saves each start's figure, in :data:`HEADLINE`'s order."""
    return [results / f"finetune_overview_{_slug(s)}.png" for s in headline]


def overview_figures(results: Path, headline: dict[str, list[Arm]] = HEADLINE) -> list[Path]:
    """One figure per start (see the module's docstring); the paths written, none on a fresh folder."""
    if not _any_saved(results, headline):
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    paths = dict(zip(headline, figure_paths(results, headline)))
    for start, rows in _rows(results, headline).items():
        fig, ax = plt.subplots(figsize=(7.5, 4.2))
        ax.axhline(rows[0]["start"]["test"]["success_once"], color="grey", lw=1.5, label="BC start (test)")
        right = max([r["env_steps"] or 0 for r in rows] + [1])
        for i, r in enumerate(rows):
            color, label = f"C{i}", r["arm"].label.replace("`", "")
            lo, hi = min(r["tests"]), max(r["tests"])
            if r["curve"]:
                steps = [c["env_steps"] for c in r["curve"]]
                ax.plot(steps, [c["mean"] for c in r["curve"]], "o-", ms=3, color=color, label=label)
                ax.fill_between(
                    steps,
                    [c["min"] for c in r["curve"]],
                    [c["max"] for c in r["curve"]],
                    color=color,
                    alpha=0.15,
                )
            if r["env_steps"]:  # an online or data arm's test, at its env steps
                ax.errorbar(
                    [r["env_steps"]],
                    [r["mean"]],
                    # (equal seeds: the float mean may sit a rounding error outside its min and max)
                    yerr=[[max(r["mean"] - lo, 0.0)], [max(hi - r["mean"], 0.0)]],
                    fmt="D",
                    ms=7,
                    color=color,
                    mec="black",
                    capsize=3,
                    label=None if r["curve"] else label,
                )
            else:  # no env step of its own: its test as a level
                ax.axhline(r["mean"], color=color, ls="--", lw=1.2, label=f"{label} (test)")
        ax.set_xlim(-0.03 * right, 1.05 * right)
        ax.set_ylim(-0.05, 1.05)
        ax.set_xlabel("env steps")
        ax.set_ylabel("success_once")
        ax.set_title(f"{start}: start test {rows[0]['start']['test']['success_once']:.2f}", fontsize=9)
        fig.text(
            0.01,
            0.01,
            "lines: validation (50 episodes), band min-max over seeds; diamonds with bars and "
            "dashes: test (100 episodes per seed), mean and min-max",
            fontsize=7,
        )
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6.5, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        fig.tight_layout(rect=(0, 0.04, 1, 1))
        fig.savefig(paths[start], dpi=110)
        plt.close(fig)
        written.append(paths[start])
    return written
