"""The RESULTS.md sections of success, convergence, ablations, multi-modality and the scripted experts:
``main_job.json`` (``success/bench_main_job``), ``success_*.json`` (``success/bench_success``, one table
for every file), ``training_*.json``, ``open_loop_*.json``, ``ablations_*.json``, ``multimodal.json``,
``pusht_modes.json`` and the experts' files."""

from __future__ import annotations

from typing import Any

from benchmarks.lib.stats import convergence_steps
from benchmarks.report.tables import interval, num, table
from l1flow_rl.workspace.run_clock import CPU_SCOPE

__all__ = [
    "render_ablations",
    "render_experts",
    "render_main_job",
    "render_multimodal",
    "render_network_success",
    "render_open_loop",
    "render_pusht_modes",
    "render_success",
    "render_training_runs",
]


def render_main_job(d: dict) -> str:
    """One row per fresh run of the plain command, and the verdict over all of them."""
    rows = []
    for r in d["runs"]:
        seeds = r.get("eval_seeds") or {}
        split = f"{r.get('eval_split', '?')} seeds from {seeds.get('first', '?')}" if seeds else "–"
        rows.append(
            [
                r["seed"],
                r["wall_seconds"],
                r["wall_over_budget"],
                r.get("demo_seconds"),
                r.get("train_seconds"),
                r.get("cpu_seconds"),
                r.get("steps"),
                ", ".join(f"{v:.2f}" for _, v in r.get("validation", [])) or "–",
                r["success_once"],
                interval(r.get("success_once_ci95")),
                r["eval_episodes"],
                split,
            ]
        )
    text = table(
        [
            "training seed",
            "wall s",
            f"of {d['budget_seconds'] / 60:.0f}-min budget",
            "demos s",
            "train s",
            "CPU s",
            "steps",
            "validation curve",
            "test success_once",
            "95 % interval",
            "episodes",
            "test seeds",
        ],
        rows,
    )
    verdict = "meets" if d["meets_targets"] else "does not meet"
    # the bench passes the test's episode count itself: any other override departs from the main job
    changed = [o for o in d.get("overrides", []) if not o.startswith("eval.episodes=")]
    command = f"`l1flow-rl train {' '.join(changed)}`" if changed else "the plain `l1flow-rl train`"
    return (
        f"{text}\n\nManiSkill PushCube (state), {command}, each run from a fresh data "
        f"directory (demonstrations made again). Mean success_once {d['success_once_mean']:.3f}, lowest "
        f"{d['success_once_min']:.2f}, longest wall {d['wall_seconds_max']:,.0f} s: the job {verdict} its "
        f"targets (success_once ≥ {d['target_success_once']} over ≥ {d['target_episodes']} test episodes "
        f"within {d['budget_seconds'] / 60:.0f} minutes, in every run)."
        + (f"\n\n**Caveat:** {d['caveat']}" if d.get("caveat") else "")
    )


def _success_rows(
    name: str, d: dict, notes: list[str], partial_budgets: list[str]
) -> tuple[list[list], bool]:
    """One file's rows of the success table, and whether any CPU figure counts the main process only."""
    rows, main_process_only = [], False
    for task, block in d["tasks"].items():
        for label, b in block.items():
            metric = b.get("metric", "success_once")  # PushT's headline is Diffusion Policy's score
            s, m = b["success_once"], b.get(metric, b["success_once"])
            steps = [f"≥ {x}" if rising else str(x) for x, rising in convergence_steps(b)]
            headline = "–" if metric == "success_once" else f"{metric} {num(m['mean'])} ± {num(m['std'])}"
            budget = [r for r in b.get("per_seed", []) if r.get("steps")]
            trained = ", ".join(sorted({str(r["steps"]) for r in budget})) or "–"
            # A run resumed from a checkpoint older than the per-run totals counts only its last
            # invocation (seconds_since_step > 0): its CPU seconds would understate the budget.
            whole = [r for r in budget if not r.get("seconds_since_step")]
            timed = [r for r in whole if r.get("cpu_seconds")]
            cpu_mean: Any = sum(r["cpu_seconds"] for r in timed) / len(timed) if timed else None
            if any(r.get("cpu_seconds_scope") != CPU_SCOPE for r in timed):
                cpu_mean, main_process_only = f"{num(cpu_mean)} †", True
            if partial := len(budget) - len(whole):
                partial_budgets.append(f"{task} {label}: {partial} run(s)")
            rows.append([f"`{name}`", task, label, headline, s["mean"], s["std"]])
            rows[-1] += [_pooled_interval(b.get("per_seed", [])), s["n"], ", ".join(steps) or "–", trained]
            rows[-1].append(cpu_mean)
            if b.get("validation_sampler"):
                notes.append(f"{task} {label}: validation curve under {b['validation_sampler']}")
    return rows, main_process_only


def _setting(name: str, d: dict) -> str | None:
    a = d.get("args") or {}
    if not (a.get("demos") and a.get("steps")):
        return None
    labels = {label for block in d["tasks"].values() for label in block}
    legend = [
        meaning
        for suffix, meaning in (
            ("_maniskill_protocol", "`_maniskill_protocol`: re-scored under ManiSkill's evaluation protocol"),
            ("_ddim16", "`ddpm_ddim16`: the DDPM network under DDIM-16"),
        )
        if any(suffix in label for label in labels)
    ]
    text = (
        f"`{name}`: {a['demos']} demonstrations, {a['steps']:,} training steps, validation every "
        f"{a.get('eval_every', '?'):,} steps, {a.get('eval_episodes', '?')} test episodes per seed"
        + (f" ({'; '.join(legend)})" if legend else "")
    )
    if a.get("extra"):
        text += "; overrides for every run: " + ", ".join(f"`{o}`" for o in a["extra"])
    return text + "."


def render_success(files: list[tuple[str, dict]]) -> str:
    """Every success file in one table, a row per task and method, then each file's setting."""
    rows, notes, partial_budgets, main_process_only = [], [], [], False
    for name, d in files:
        file_rows, main_only = _success_rows(name, d, notes, partial_budgets)
        rows += file_rows
        main_process_only |= main_only
    header = ["file", "task", "method", "headline", "success_once (mean)", "std over seeds", "95 % interval"]
    header += ["seeds", "steps to 90 %", "steps trained", "CPU s per run"]
    text = table(header, rows)
    text += (
        "\n\n95 % interval: Wilson's, over every seed's test episodes pooled. Steps to 90 %: per seed, "
        "the first validation step within 90 % of that seed's best (≥: first reached at the last validation, "
        "so the curve was still rising and the figure is a lower bound). The test figures are the "
        "validation-chosen checkpoint's. Runs shared the cores with other runs, so CPU seconds, not wall "
        "time, are the budget figure."
    )
    if notes:
        text += " " + "; ".join(notes) + " (its test figures use its own sampler)."
    if main_process_only:
        text += (
            " †: the runs' own processes only; their simulator workers' CPU (started through a forkserver) "
            "was not yet counted when they ran, so the figure understates the budget."
        )
    if partial_budgets:
        text += (
            " CPU s per run leave out runs resumed from checkpoints that predate per-run totals (their "
            f"seconds cover only the last invocation): {'; '.join(partial_budgets)}."
        )
    settings = [line for name, d in files if (line := _setting(name, d))]
    if settings:
        text += "\n\nSettings:\n\n" + "\n".join(f"- {line}" for line in settings)
    return text


def _pooled_interval(per_seed: list[dict]) -> str:
    """Wilson's 95 % interval of the success rate over all seeds' test episodes together."""
    from benchmarks.report.claims import pooled_interval

    ci = pooled_interval(per_seed)
    return f"[{ci[0]:.2f}, {ci[1]:.2f}]" if ci else "–"


def render_training_runs(d: dict) -> str:
    rows = [
        [
            r["task"],
            r["policy"],
            r["demos"],
            r["steps"],
            r["wall_seconds"],
            r["success_once"],
            interval(r.get("success_once_ci95")),
            r["episodes"],
            f"{r.get('split')} from {(r.get('split_seeds') or {}).get('first')}",
        ]
        for r in d["runs"]
    ]
    text = table(
        ["task", "method", "demos", "steps", "wall s", "success_once", "95 % interval", "episodes", "seeds"],
        rows,
    )
    return text


def render_open_loop(d: dict) -> str:
    """bench_open_loop: each trained run's executed steps against the demonstrator's, same windows."""
    rows = []
    for label, m in d["methods"].items():
        per_seed = ", ".join(f"{r['l1']:.4f}" for r in d["runs"][label].values())
        rows.append([label, m["l1_mean"], m["l1_std"], m["seeds"], per_seed])
    note = (
        f"{d['windows']} windows of each run's own demonstrations (seed {d['window_seed']}), one sampled "
        "chunk each; error in normalised action units ([-1, 1] per dimension) over the executed steps."
    )
    if d.get("missing"):
        note += f" Runs without a checkpoint, left out: {len(d['missing'])}."
    return table(["method", "mean abs error", "std over seeds", "seeds", "per seed"], rows) + "\n\n" + note


def render_ablations(d: dict) -> str:
    """One row per variant: per-seed rates, the pooled interval, and the paired difference from the
    default on the same seeds (sampler swaps re-score the default's own networks, so the pairing
    removes the seed-to-seed spread that dwarfs most effects at this scale)."""
    variants = d["variants"]
    default = [r["success_once"] for r in variants.get("default", {}).get("per_seed", [])]
    rows = []
    for name, b in variants.items():
        per_seed = [r["success_once"] for r in b["per_seed"]]
        paired = [v - base for v, base in zip(per_seed, default)] if name != "default" else []
        rows.append(
            [
                name,
                b["kind"],
                " / ".join(f"{v:.2f}" for v in per_seed),
                b["success_once"]["mean"],
                _pooled_interval(b["per_seed"]),
                f"{sum(paired) / len(paired):+.3f}" if paired else "–",
            ]
        )
    a = d.get("args", {})
    setting = f"Setting: {a.get('task')}, {a.get('demos')} demonstrations, {a.get('steps')} training steps, "
    seeds = ", ".join(map(str, a.get("seeds", [])))
    setting += f"{a.get('eval_episodes')} test episodes per seed (seeds {seeds}); "
    setting += "sampler variants re-score the default network; loss variants retrain it. "
    setting += "95 % interval: Wilson's over every seed's test episodes pooled. "
    setting += "Δ: mean over seeds of (variant − default on the same seed)."
    header = ["variant", "kind", "per seed", "mean", "95 % interval", "Δ vs default"]
    return table(header, rows) + "\n\n" + setting


def render_multimodal(d: dict) -> str:
    out = [f"{d['steps']} training steps per method.\n"]
    for family, block in d["families"].items():
        rows = [
            [name, r["nfe"], f"{r['modes_hit']}/{r['num_modes']}", r["share_neither"], r["balance"]]
            for name, r in block["methods"].items()
        ]
        out.append(f"{family} ({block['num_modes']} modes):\n")
        out.append(table(["evaluation", "NFE", "modes hit", "off-mode mass", "balance"], rows) + "\n")
    return "\n".join(out)


def render_pusht_modes(d: dict) -> str:
    routes = ("left", "right", "between", "no_contact")
    rows = []
    for name, b in d["policies"].items():
        bim = b["routes_bimodal"]
        shares = [f"{num(bim['shares'][r], 2)} ({bim['counts'][r]}/{bim['n']})" for r in routes]
        rows.append(
            [
                name,
                b["score"],
                interval(b["ci95"]["score"]),
                b["success"],
                interval(b["ci95"]["success"]),
                *shares,
            ]
        )
    header = ["policy", "score", "95 %", "success", "95 %", *(f"{r} (bimodal seeds)" for r in routes)]
    expert = d["policies"].get("expert", {})
    n_bimodal = len(d["bimodal_seeds"])
    note = (
        f"Bimodal seeds: the {len(d['bimodal_seeds'])} test seeds where the expert's first way around the T "
        f"was a free choice; the route rule agrees with the planner on "
        f"{round((expert.get('agreement_on_bimodal') or 0) * n_bimodal)}/{n_bimodal}"
        " of them. `between`: the policy reached the T without "
        "going around it (what averaging a left and a right path gives)."
    )
    return table(header, rows) + "\n\n" + note


def render_experts(d: dict) -> str:
    """Scripted experts over many seeds (robosuite's rows, or PushT's single task)."""
    if "rows" in d:
        rows = [
            [r["task"], r["seeds"], r["success_rate"], r["seconds_per_episode"], r["steps_per_success_mean"]]
            for r in d["rows"]
        ]
        return table(["task", "seeds", "success", "s / episode", "steps (mean)"], rows)
    text = table(
        ["task", "seeds", "success", "mean score", "s / episode", "steps (mean)"],
        [
            [
                "pusht",
                d["seeds"],
                d["success"],
                d["mean_score"],
                d["seconds_per_episode_mean"],
                d["steps_mean"],
            ]
        ],
    )
    sides = ", ".join(f"{k} {v:.2f}" for k, v in d.get("side_share", {}).items())
    return text + (f"\n\nShare of episodes per side of the block: {sides}." if sides else "")


def _net_cell(block: dict) -> str:
    """One network's test: the headline mean with Wilson's interval over the seeds' episodes pooled."""
    metric = block.get("metric", "success_once")
    text = f"{block['success_once']['mean']:.3f} {_pooled_interval(block.get('per_seed', []))}"
    if metric != "success_once":  # PushT: Diffusion Policy's score first, its success beside
        text = f"{metric} {block[metric]['mean']:.3f}; success {text}"
    return text


def _seeds(block: dict) -> str:
    n = block["success_once"]["n"]
    return f"{n} seed{'s' * (n != 1)}"


def _cpu_per_run(block: dict) -> str:
    timed = [r["cpu_seconds"] for r in block.get("per_seed", []) if r.get("cpu_seconds")]
    return f"{sum(timed) / len(timed):,.0f}" if timed else "–"


def _episodes(block: dict) -> str:
    """Each seed's test episodes (what the protocol ran, which may differ from ``eval.episodes``)."""
    counts = sorted({r.get("episodes") for r in block.get("per_seed", []) if r.get("episodes")})
    return " / ".join(map(str, counts)) or "?"


def _every(args: dict) -> str:
    every = args.get("eval_every")
    return f"{every:,}" if isinstance(every, int) else "–"


def _steps_to_90(block: dict) -> str:
    steps = [s for s, _ in convergence_steps(block)]
    return f"{sum(steps) / len(steps):,.0f}" if steps else "–"


def render_network_success(d: dict) -> str:
    """The MLP denoiser's L1 Flow against the UNet's, task by task: the test of the weights each run
    ships, the MLP's last weights, whether the MLP's mean lies in the UNet's interval, convergence and
    each run's CPU seconds."""
    from benchmarks.report.claims import pooled_interval

    rows, verdicts = [], {"inside": 0, "above": 0, "below": 0}
    for task, t in d["tasks"].items():
        unet, mlp = t["unet"]["block"], t["mlp"]["l1flow"]
        last = t["mlp"].get("l1flow_last_weights")
        ci = pooled_interval(unet.get("per_seed", [])) or (0.0, 1.0)
        mean = mlp["success_once"]["mean"]
        verdict = "below" if mean < ci[0] else "above" if mean > ci[1] else "inside"
        verdicts[verdict] += 1
        ua, ma = t["unet"]["args"], t["args"]
        rows.append(
            [
                task,
                ma["demos"],
                f"{_net_cell(unet)} ({ua['steps']:,} steps, {_seeds(unet)} × {_episodes(unet)}; "
                f"`{t['unet']['file']}`)",
                f"{_net_cell(mlp)} ({ma['steps']:,} steps, {_seeds(mlp)} × {_episodes(mlp)})",
                _net_cell(last) if last else "–",
                verdict,
                f"{_steps_to_90(unet)} / {_steps_to_90(mlp)} (every {_every(ua)} / {_every(ma)})",
                f"{_cpu_per_run(unet)} / {_cpu_per_run(mlp)}",
            ]
        )
    header = ["task", "demos", "UNet L1 Flow, shipped weights", "MLP L1 Flow, shipped weights"]
    header += ["MLP, last weights", "MLP's mean against UNet's interval"]
    header += ["steps to 90 % (UNet / MLP; validated)"]
    header += ["CPU s per run (UNet / MLP)"]
    text = table(header, rows)
    return text + (
        f"\n\nThe MLP's mean success_once lies inside the UNet's 95 % interval on {verdicts['inside']}, "
        f"above it on {verdicts['above']} and below it on {verdicts['below']} of {len(rows)} tasks. "
        "Each network's cell: mean success_once over seeds with Wilson's 95 % interval over their "
        "test episodes pooled (PushT: Diffusion Policy's score first). The UNet's figures are the published "
        "file named in its cell, measured under that file's own budget and checkpoint rule (its section "
        "above); where its training steps differ from the MLP's, the two rows compare networks at "
        "different step counts, and steps to 90 % of the best are no finer than each side's validation "
        "cadence. The per-step costs are in 'State denoisers: the UNet against the MLP'. "
        "CPU s per run: the whole run, its demonstrations, validations and test included."
    )
