"""The paper's second table (``distillation_<task>.json``, ``success/bench_distillation``): L1 Flow
against Diffusion Policy under DDPM, DDIM and EDM, Consistency Policy and OneDP, one row per method
and NFE; and its claim's rows for the summary ("comparable to distillation-based methods with 5-7×
less training")."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from benchmarks.report.tables import interval, num, table

__all__ = ["DISTILLED", "distillation_claim_rows", "render_distillation"]

#: the rows that are distillation-based fast policies (a student trained from a teacher)
DISTILLED = ("consistency_cp3", "consistency", "onedp_d", "onedp_s", "onedp_d_ddpm", "onedp_s_ddpm")
#: the least of the paper's training advantage: the distilled methods' epochs over L1 Flow's (5-7×)
PAPER_LEAST_RATIO = 5.0


def _pooled(row: dict[str, Any]) -> tuple[float, float] | None:
    from benchmarks.report.claims import pooled_interval

    return pooled_interval(row["per_seed"])


def _mean(values: list[float] | None) -> float | None:
    return sum(values) / len(values) if values else None


def _to_90(row: dict[str, Any]) -> float | None:
    """Mean steps to 90 % of its best over the seeds whose validation rose above 0, its teacher's
    steps counted (None: a re-scoring, or no such seed)."""
    return _mean([s for s in row.get("steps_to_90pct_of_best_with_teacher") or [] if s is not None])


def _headline(row: dict[str, Any]) -> str:
    """The protocol's headline metric (PushT: Diffusion Policy's score; else success_once), its mean."""
    metric = row.get("metric", "success_once")
    return f"{metric} {row[metric]['mean']:.3f}"


def _training(row: dict[str, Any]) -> str:
    steps, teacher = _mean(row["training_steps"]), _mean(row["teacher_steps"])
    return f"{steps:,.0f}" + (f" ({teacher:,.0f} teacher)" if teacher else "")


def _verdict(below: list[str], ratios: dict[str, float], names: dict[str, str]) -> str:
    """The claim's verdict from the distilled rows whose interval lies above L1 Flow's (``below``)
    and each distilled row's training to 90 % of its best over L1 Flow's (``ratios``)."""
    if below:
        return "below " + ", ".join(below)
    if not ratios:
        return "comparable or better success; training not measured"
    slower = [names[k] for k, v in ratios.items() if v <= 1]
    if slower:
        return "comparable or better success; not less training than " + ", ".join(slower)
    least = min(ratios.values())
    if least >= PAPER_LEAST_RATIO:
        return "holds"
    return f"comparable or better success, with {least:.2g}× less training at the least (paper: 5-7×)"


def render_distillation(d: dict) -> str:
    """One row per method and NFE: success with the pooled interval and each seed, the training the
    weights went through (the teacher's included), steps to 90 % of the best and the batch-1 latency."""
    rows = []
    for label, r in d["rows"].items():
        seeds = ", ".join(f"{s['value']:.2f}" for s in r["per_seed"])  # the headline metric
        to_90 = _to_90(r)
        latency = r["latency_batch1_ms"]["wall_ms"]
        ratio = r.get("latency_vs_l1flow")
        rows.append(
            [
                r["method"],
                f"`{label}`",
                r["nfe"],
                _headline(r),
                interval(list(_pooled(r) or []) or None),
                seeds,
                _training(r),
                f"{to_90:,.0f}" if to_90 is not None else "–",
                f"{num(latency)}" + (f" ({num(ratio)}×)" if ratio is not None else ""),
            ]
        )
    a = d["args"]
    header = ["method", "row", "NFE", "headline", "success_once 95 % interval", "per seed (headline)"]
    header += ["training steps", "steps to 90 % of best", "batch-1 ms (× L1 Flow)"]
    text = table(header, rows)
    missing = d.get("missing_rows") or []
    return text + (
        f"\n\n{d['task']}, {a['demos']} demonstrations, `network={a['network']}`; "
        f"{a['eval_episodes']} test episodes per seed. Teachers (DDPM, EDM) and L1 "
        "Flow train on the success grids' budget; a student trains from its own seed's teacher for the "
        "share of the teacher's budget its paper gives (CP 45 %, OneDP 2 %). Training steps: every stage "
        "the shipped weights went through, the teacher's to its shipped checkpoint included (the paper "
        "counts a student's epochs with its teacher's). Steps to 90 % of best: on the validation "
        "curve, a student's shifted by its teacher's steps; a re-scoring has no curve of its own. "
        "Headline: the protocol's first metric (PushT: Diffusion Policy's score), mean over seeds; "
        "interval: success_once's, Wilson's 95 % over every seed's test episodes pooled. Latency: the "
        f"seed-0 network under the row's sampler, median of {a.get('latency_rounds', '?')} rounds in one "
        "run, one torch thread."
        + (f" Rows without a finished evaluation: {', '.join(f'`{m}`' for m in missing)}." if missing else "")
    )


def distillation_claim_rows(results: Path, load: Any) -> list[list[str]]:
    """The fifth claim per distillation file: L1 Flow's success against each distilled row's
    (comparable unless its interval lies wholly below one), and the training each distilled row needed
    to come within 90 % of its best, teacher included, as a multiple of L1 Flow's."""
    rows = []
    for path in sorted(results.glob("distillation_*.json")):
        d = load(path)
        if d is None or "l1flow" not in d["rows"]:
            continue
        own = d["rows"]["l1flow"]
        distilled = {k: d["rows"][k] for k in DISTILLED if k in d["rows"]}
        if not distilled:
            continue
        names = {k: f"{r['method']} {r['nfe']}" for k, r in distilled.items()}
        metric = own.get("metric", "success_once")
        mine, mine_ci = own[metric]["mean"], _pooled(own)
        if metric == "success_once":  # Wilson's intervals over the seeds' test episodes pooled
            above = [k for k, r in distilled.items() if (ci := _pooled(r)) and mine_ci and mine_ci[1] < ci[0]]
        else:  # PushT's score carries no interval here: a higher mean
            above = [k for k, r in distilled.items() if r[metric]["mean"] > mine]
        below = [names[k] for k in above]
        l1_steps, steps = _to_90(own), {k: _to_90(r) for k, r in distilled.items()}
        ratios = {k: v / l1_steps for k, v in steps.items() if l1_steps and v is not None}
        cells = [f"{names[k]} NFE: {r[metric]['mean']:.3f}" for k, r in distilled.items()]
        if ratios:
            lo, hi = f"{min(ratios.values()):.2g}", f"{max(ratios.values()):.2g}"
            span = lo if lo == hi else f"{lo}-{hi}"
            cells.append(f"training to 90 % of best (teacher's included): {span}× L1 Flow's")
        counts = sorted({r["success_once"]["n"] for r in (own, *distilled.values())})
        seeds = f"{counts[0]}-{counts[-1]}" if len(counts) > 1 else str(counts[0])
        rows.append(
            [
                "comparable to distillation-based methods with 5-7× less training",
                f"{d['task']} ({seeds} seed{'s' * (seeds != '1')} per row, `{path.name}`)",
                f"{metric} {mine:.3f}" + (f"; {l1_steps:,.0f} steps to 90 % of best" if l1_steps else ""),
                "; ".join(cells),
                _verdict(below, ratios, names),
            ]
        )
    return rows
