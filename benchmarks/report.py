"""``benchmarks/RESULTS.md`` and the README's results summary, built from the JSON the benchmark
scripts saved: no number in either is typed by hand.

    .venv/bin/python -m benchmarks.report            # rewrite RESULTS.md and the README's summary
    .venv/bin/python -m benchmarks.report --check    # exit 1, naming each stale section, if either differs

RESULTS.md holds every file's section, grouped by what it measures, each under a heading that names
its source file; the README holds only the summary between its markers (the claims table and the
overview figure) and links to RESULTS.md. Each results file has a renderer keyed by its name; a file
without one is listed by name, so nothing saved is silently left out. Quick-mode files
(``"quick": true``) are never reported.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchmarks import finetune_overview
from benchmarks.export_report import render_export_latency
from benchmarks.finetune_report import (
    render_critic_bias,
    render_failure_phases,
    render_finetune_cost,
    render_finetune_online,
    render_finetune_shock,
    render_fql_distill,
    render_noise_authority,
    render_noise_draw,
)
from benchmarks.sweep import convergence_steps
from l1flow_rl.workspace.run_clock import CPU_SCOPE

__all__ = ["build_finetune_block", "build_results", "build_summary", "main", "stale_sections"]

BEGIN, END = "<!-- results:begin (python -m benchmarks.report) -->", "<!-- results:end -->"
#: the README's fine-tuning table (optional: a README without these markers has none)
FT_BEGIN, FT_END = "<!-- finetune:begin (python -m benchmarks.report) -->", "<!-- finetune:end -->"
RESULTS = Path("benchmarks/results")
#: the generated document of every results file's section
RESULTS_DOC = Path("benchmarks/RESULTS.md")
#: the figure of every success file's curves, which the report draws from them beside its table
OVERVIEW_PLOT = "success_overview.png"


def _num(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, float):
        return f"{value:,.0f}" if abs(value) >= 1000 else f"{value:.{digits}g}"
    return str(value)


def _table(header: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_num(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def _runs_machines(d: dict) -> str | None:
    """The machines a collected success file's runs recorded as they ended (None: none recorded)."""
    seeds = [
        r
        for by_policy in (d.get("tasks") or {}).values()
        for entry in by_policy.values()
        for r in entry.get("per_seed", [])
    ]
    machines = [r["machine"] for r in seeds if isinstance(r.get("machine"), dict)]
    if not machines:
        return None
    kinds = sorted({f"{m.get('cpu', '?')}, torch threads {m.get('torch_threads')}" for m in machines})
    loads = [m["load_average_1min"] for m in machines if "load_average_1min" in m]
    text = "; ".join(kinds)
    if loads:
        text += f", load {min(loads)}-{max(loads)} as they ended"
    if len(machines) < len(seeds):
        text += f" ({len(machines)} of {len(seeds)} seed records carry it)"
    return text


def _machine(d: dict) -> str:
    m = d.get("machine") or d.get("machine_at_start")
    if m is None and "cpu_count" in d:
        load = d.get("loadavg_before") or d.get("loadavg_after")
        return f"{d['cpu_count']} cores" + (f", load {load[0]:.2f}" if load else "")
    if isinstance(m, dict) and (d.get("args") or {}).get("collect_only"):
        # the collecting process's threads and load say nothing of the runs, which trained earlier
        where = f"{m.get('cpu', '?')}, {m.get('cores')} cores (where the runs were collected"
        runs = _runs_machines(d)
        if runs is None:
            return f"{where}; they trained earlier, and this file holds none of their thread counts or load)"
        return f"{where}); the runs: {runs}"
    if isinstance(m, dict):
        parts = [m.get("cpu", "?"), f"{m.get('cores')} cores", f"torch threads {m.get('torch_threads')}"]
        if "load_average_1min" in m:
            parts.append(f"load {m['load_average_1min']}")
        if m.get("gpu"):
            parts += [m["gpu"], f"torch {m.get('torch')}"]
        return ", ".join(str(p) for p in parts)
    return str(m)


def _interval(ci: list | None) -> str:
    return f"[{ci[0]:.2f}, {ci[1]:.2f}]" if ci else "–"


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
                _interval(r.get("success_once_ci95")),
                r["eval_episodes"],
                split,
            ]
        )
    table = _table(
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
    return (
        f"{table}\n\nManiSkill PushCube (state), the plain `l1flow-rl train`, each run from a fresh data "
        f"directory (demonstrations made again). Mean success_once {d['success_once_mean']:.3f}, lowest "
        f"{d['success_once_min']:.2f}, longest wall {d['wall_seconds_max']:,.0f} s: the job {verdict} its "
        f"targets (success_once ≥ {d['target_success_once']} over ≥ {d['target_episodes']} test episodes "
        f"within {d['budget_seconds'] / 60:.0f} minutes, in every run)."
    )


def render_latency(d: dict) -> str:
    net = d.get("network") or {}
    out = [
        f"Network: {net.get('task', 'state')} ({_num(net.get('parameters'))} parameters, UNet "
        f"{'/'.join(map(str, net.get('down_dims', [])))}).\n"
    ]
    for batch, block in d["inference"].items():
        rows = [
            [name, d["nfe"].get(name), ms["wall_ms"], ms["cpu_ms"], block["slowdown_vs_l1flow"][name]]
            for name, ms in block["ms"].items()
        ]
        out.append(f"Per-chunk latency, {batch}, {d['machine'].get('device', 'cpu')}:\n")
        out.append(_table(["method", "NFE", "wall ms", "CPU ms", "× L1 Flow"], rows))
        out.append(f"\nL1 Flow over its floor (encoder + 2 UNet forwards): {block['l1flow_over_floor']}×\n")
    if "train_step_ms" in d:
        t = d["train_step_ms"]
        rows = [[k, v["wall_ms"], v["cpu_ms"]] for k, v in t["ms"].items()]
        out.append(f"Training step, batch {t['batch']}:\n")
        out.append(_table(["loss", "wall ms", "CPU ms"], rows))
    return "\n".join(out)


def render_latency_cuda(d: dict) -> str:
    """bench_latency_cuda: batch-1 chunks on the GPU, eager and captured, against diffusers' loops."""
    out = []
    if d.get("cudnn_benchmark"):
        out.append("cuDNN autotuning on (every arm).\n")
    for name, block in d["networks"].items():
        rows = [[method, ms["wall_ms"], block["chunks_per_s"][method]] for method, ms in block["ms"].items()]
        out.append(f"{name} network ({_num(block['parameters'])} parameters), batch 1:\n")
        out.append(_table(["method", "wall ms", "chunks/s"], rows))
        ratios = [
            f"{key.replace('_', ' ')} {block[key]}×"
            for key in (
                "cuda_graph_speedup_over_eager",
                "cuda_graph_speedup_over_diffusers_ddpm100",
                "cuda_graph_speedup_over_diffusers_ddim16",
                "eager_speedup_over_diffusers_ddpm100",
                "eager_speedup_over_diffusers_ddim16",
            )
            if key in block
        ]
        out.append("\n" + "; ".join(ratios) + ".\n")
        for key, err in block.get("errors", {}).items():
            out.append(f"{key}: not measured ({err})\n")
    return "\n".join(out)


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
    return _table(["method", "mean abs error", "std over seeds", "seeds", "per seed"], rows) + "\n\n" + note


def render_multimodal(d: dict) -> str:
    out = [f"{d['steps']} training steps per method.\n"]
    for family, block in d["families"].items():
        rows = [
            [name, r["nfe"], f"{r['modes_hit']}/{r['num_modes']}", r["share_neither"], r["balance"]]
            for name, r in block["methods"].items()
        ]
        out.append(f"{family} ({block['num_modes']} modes):\n")
        out.append(_table(["evaluation", "NFE", "modes hit", "off-mode mass", "balance"], rows) + "\n")
    return "\n".join(out)


def render_success(d: dict) -> str:
    rows, notes, partial_budgets, main_process_only = [], [], [], False
    for task, block in d["tasks"].items():
        for label, b in block.items():
            metric = b.get("metric", "success_once")  # PushT's headline is Diffusion Policy's score
            s, m = b["success_once"], b.get(metric, b["success_once"])
            steps = [f"≥ {x}" if rising else str(x) for x, rising in convergence_steps(b)]
            headline = "–" if metric == "success_once" else f"{metric} {_num(m['mean'])} ± {_num(m['std'])}"
            budget = [r for r in b.get("per_seed", []) if r.get("steps")]
            trained = ", ".join(sorted({str(r["steps"]) for r in budget})) or "–"
            # A run resumed from a checkpoint older than the per-run totals counts only its last
            # invocation (seconds_since_step > 0): its CPU seconds would understate the budget.
            whole = [r for r in budget if not r.get("seconds_since_step")]
            timed = [r for r in whole if r.get("cpu_seconds")]
            cpu_mean: Any = sum(r["cpu_seconds"] for r in timed) / len(timed) if timed else None
            if any(r.get("cpu_seconds_scope") != CPU_SCOPE for r in timed):
                cpu_mean, main_process_only = f"{_num(cpu_mean)} †", True
            if partial := len(budget) - len(whole):
                partial_budgets.append(f"{task} {label}: {partial} run(s)")
            rows.append(
                [task, label, headline, s["mean"], s["std"], _pooled_interval(b.get("per_seed", [])), s["n"]]
            )
            rows[-1] += [", ".join(steps) or "–", trained, cpu_mean]
            if b.get("validation_sampler"):
                notes.append(f"{task} {label}: validation curve under {b['validation_sampler']}")
    header = ["task", "method", "headline", "success_once (mean)", "std over seeds", "95 % interval"]
    header += ["seeds", "steps to 90 %", "steps trained", "CPU s per run"]
    text = _table(header, rows)
    text += (
        "\n\n95 % interval: Wilson's, over every seed's test episodes pooled. Steps to 90 %: per seed, "
        "the first validation step within 90 % of that seed's best (≥: first reached at the last validation, "
        "so the curve was still rising and the figure is a lower bound)."
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
    a = d.get("args") or {}
    if a.get("demos") and a.get("steps"):
        labels = {label for block in d["tasks"].values() for label in block}
        legend = [
            meaning
            for suffix, meaning in (
                (
                    "_maniskill_protocol",
                    "`_maniskill_protocol`: re-scored under ManiSkill's evaluation protocol",
                ),
                ("_ddim16", "`ddpm_ddim16`: the DDPM network under DDIM-16"),
            )
            if any(suffix in label for label in labels)
        ]
        text += (
            f"\n\nSetting: {a['demos']} demonstrations, {a['steps']:,} training steps, validation every "
            f"{a.get('eval_every', '?'):,} steps; the test figures are the validation-chosen checkpoint's on "
            f"{a.get('eval_episodes', '?')} test episodes per seed"
            + (f" ({'; '.join(legend)})" if legend else "")
            + ". Runs shared the cores with other runs, so CPU seconds, not wall time, are the budget figure."
        )
        if a.get("extra"):
            text += " Overrides for every run: " + ", ".join(f"`{o}`" for o in a["extra"]) + "."
    return text


def _pooled_interval(per_seed: list[dict]) -> str:
    """Wilson's 95 % interval of the success rate over all seeds' test episodes together."""
    from benchmarks.claims import pooled_interval

    ci = pooled_interval(per_seed)
    return f"[{ci[0]:.2f}, {ci[1]:.2f}]" if ci else "–"


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
    return _table(header, rows) + "\n\n" + setting


def render_env_throughput(d: dict) -> str:
    rows = []
    for r in d["rows"]:
        for name, a in r["adapters"].items():
            rows.append([r["setting"], name, r["raw_steps_per_s"], a["steps_per_s"], a["over_raw"]])
    return _table(["setting", "adapter", "raw steps/s", "adapter steps/s", "× raw"], rows)


def render_sampler(d: dict) -> str:
    return _table(
        ["storage", "chunks/s sampled", "× training rate"],
        [
            ["state", d["state_chunks_per_s"], d["state_sampler_over_train"]],
            ["rgb 128²", d["rgb128_chunks_per_s"], d["rgb128_sampler_over_train"]],
        ],
    )


def render_experts(d: dict) -> str:
    """Scripted experts over many seeds (robosuite's rows, or PushT's single task)."""
    if "rows" in d:
        rows = [
            [r["task"], r["seeds"], r["success_rate"], r["seconds_per_episode"], r["steps_per_success_mean"]]
            for r in d["rows"]
        ]
        return _table(["task", "seeds", "success", "s / episode", "steps (mean)"], rows)
    table = _table(
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
    return table + (f"\n\nShare of episodes per side of the block: {sides}." if sides else "")


def render_sim_throughput(d: dict) -> str:
    """Adapter against the raw simulator, steps/s (PushT's per-task blocks or robosuite's rows)."""
    if "rows" in d:
        rows = [
            [r["setting"], r["raw_steps_per_s"], r["make_env_steps_per_s"], r["make_env_over_raw"]]
            for r in d["rows"]
        ]
        return _table(["setting", "raw steps/s", "make_env steps/s", "× raw"], rows)
    rows = []
    for task, block in d.items():
        if isinstance(block, dict) and "steps_per_s" in block:
            for name, rate in block["steps_per_s"].items():
                rows.append([task, name, rate, block["ratio_to_raw"][name]])
    return _table(["task", "setting", "steps/s", "× raw"], rows)


def render_image_latency(d: dict) -> str:
    rows = [
        [
            batch,
            b["ms"]["actor"]["wall_ms"],
            b["ms"]["actor"]["cpu_ms"],
            b["ms"]["floor"]["cpu_ms"],
            b["actor_over_floor"],
        ]
        for batch, b in d["inference"].items()
    ]
    return _table(["batch", "actor wall ms", "actor CPU ms", "floor CPU ms", "actor / floor (wall)"], rows)


def render_image_train(d: dict) -> str:
    s = d["setup"]
    return _table(
        ["batch", "image", "samples/s from the buffer", "samples/s resident", "buffer / resident"],
        [
            [
                s["batch"],
                "×".join(map(str, s["image"])),
                d["samples_per_s"]["buffer"],
                d["samples_per_s"]["resident"],
                d["buffer_over_resident"],
            ]
        ],
    )


def render_train_throughput(d: dict) -> str:
    rows = []
    for net, block in d["networks"].items():
        for setting, r in block["settings"].items():
            rows.append(
                [
                    net,
                    setting,
                    r["samples_per_s"]["trainer"],
                    r["samples_per_s"]["model"],
                    r["trainer_over_model"],
                ]
            )
    table = _table(
        ["network", "setting", "trainer samples/s", "bare update samples/s", "trainer / bare"], rows
    )
    return table


def render_training_runs(d: dict) -> str:
    rows = [
        [
            r["task"],
            r["policy"],
            r["demos"],
            r["steps"],
            r["wall_seconds"],
            r["success_once"],
            _interval(r.get("success_once_ci95")),
            r["episodes"],
            f"{r.get('split')} from {(r.get('split_seeds') or {}).get('first')}",
        ]
        for r in d["runs"]
    ]
    table = _table(
        ["task", "method", "demos", "steps", "wall s", "success_once", "95 % interval", "episodes", "seeds"],
        rows,
    )
    return table


def render_pusht_modes(d: dict) -> str:
    routes = ("left", "right", "between", "no_contact")
    rows = []
    for name, b in d["policies"].items():
        bim = b["routes_bimodal"]
        shares = [f"{_num(bim['shares'][r], 2)} ({bim['counts'][r]}/{bim['n']})" for r in routes]
        rows.append(
            [
                name,
                b["score"],
                _interval(b["ci95"]["score"]),
                b["success"],
                _interval(b["ci95"]["success"]),
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
    return _table(header, rows) + "\n\n" + note


def render_flow_q(d: dict) -> str:
    labels = {
        "bc": "BC (the start)",
        "flowq_offline": "+ FlowQ offline",
        "flowq_online": "+ FlowQ offline + online",
        "bc_continued": "continued BC (same updates)",
        "bc_one_step": "BC (the start), one-step sampler",
        "bc_continued_one_step": "continued BC, one-step sampler",
    }
    fields = ("episodes", "updates", "env_steps", "wall_seconds")
    rows = [
        [labels.get(name, name), a["success_once"], _interval(a.get("ci95")), *(a.get(f) for f in fields)]
        for name, a in d["arms"].items()
    ]
    header = ["arm", "success_once (test)", "95 % interval", "episodes", "updates", "env steps", "wall s"]
    if d.get("extra_test_episodes"):  # each arm also scored on further test seeds: the pooled figure
        header += ["pooled success_once", "pooled 95 %", "pooled episodes"]
        for row, a in zip(rows, d["arms"].values()):
            pooled = a.get("pooled") or {}
            row += [pooled.get("success_once"), _interval(pooled.get("ci95")), pooled.get("episodes")]
    gain = d.get("gain_over_continued_bc")
    note = f"Setting: {d['setting']}. Gain of online FlowQ over continued BC: {_num(gain)}"
    best = d.get("gain_over_best_continued_bc")
    note += "." if best is None else f"; over the better of its two samplers: {_num(best)}."
    data = d.get("data") or {}
    if "noise" in data:  # which rollouts: files of the same name may come from other checkpoints
        note += (
            f" Data: {data['episodes']} episodes ({data['steps']} steps) of {data['checkpoint']} with "
            f"action noise {data['noise']}, success rate {_num(data['success_rate'])}."
        )
    offline_cont = d.get("gain_offline_over_best_continued_bc")
    if offline_cont is not None:
        note += f" Offline FlowQ over continued BC (the better of its two samplers): {_num(offline_cont)}."
    offline = d.get("gain_offline_over_best_bc")
    if offline is not None:
        note += f" Offline FlowQ over the best BC arm (either sampler, the start included): {_num(offline)}."
    pooled = d.get("pooled_gains")
    if pooled:
        note += (
            f" Pooled over test and extra episodes: offline FlowQ over continued BC (the better of its two "
            f"samplers) {_num(pooled['gain_offline_over_best_continued_bc'])}, over the best BC arm "
            f"{_num(pooled['gain_offline_over_best_bc'])}; online FlowQ over continued BC "
            f"{_num(pooled['gain_over_best_continued_bc'])}."
        )
    return _table(header, rows) + "\n\n" + note


#: RESULTS.md's groups in order, each a heading and its files' (name pattern, section title, renderer)
GROUPS: dict[str, list[tuple[str, str, Callable[[dict], str]]]] = {
    "Success, convergence and ablations": [
        (r"main_job\.json", "Main job", render_main_job),
        (r"success_.*\.json", "Success and convergence", render_success),
        (r"training_.*\.json", "Trained policies (default budget, one seed)", render_training_runs),
        (r"open_loop_.*\.json", "Open-loop action error of the trained runs", render_open_loop),
        (r"ablations_.*\.json", "Ablations", render_ablations),
    ],
    "Multi-modality": [
        (r"multimodal\.json", "Multi-modality (toy)", render_multimodal),
        (r"pusht_modes\.json", "Multi-modality on PushT: which way around the T", render_pusht_modes),
    ],
    "Speed: inference and training": [
        (r"latency\.json", "Inference latency and training step (state network)", render_latency),
        (r"latency_image\.json", "Inference latency (image network)", render_latency),
        (r"latency_samplers_cuda\.json", "CUDA latency, every sampler (state network)", render_latency),
        (r"latency_samplers_cuda_image\.json", "CUDA latency, every sampler (image network)", render_latency),
        (r"latency_cuda.*\.json", "CUDA latency at batch 1: eager, graph, compile", render_latency_cuda),
        (r"image_latency\.json", "Image policy: latency against its floor", render_image_latency),
        (r"image_train\.json", "Image policy: training from the memory-mapped buffer", render_image_train),
        (r"train_throughput_.*\.json", "Training step against the bare update", render_train_throughput),
        (r"export_latency\.json", "Deployable policy: exported program and ONNX", render_export_latency),
    ],
    "Fine-tuning": [
        (
            r"finetune_online_.*\.json",
            "Online fine-tuning: success against env steps",
            render_finetune_online,
        ),
        (r"finetune_cost_.*\.json", "Fine-tuning: cost of an update and of acting", render_finetune_cost),
        (
            r"finetune_shock_.*\.json",
            "Fine-tuning: what the first updates do to the BC flow's fit, per optimiser start",
            render_finetune_shock,
        ),
        (
            r"noise_authority.*\.json",
            "Steering authority of the input noise (what DSRL can move)",
            render_noise_authority,
        ),
        (
            r"noise_draw_.*\.json",
            "Validation figures and the sampler's noise draw",
            render_noise_draw,
        ),
        (
            r"diagnose_.*\.json",
            "Failure anatomy: the phase each episode ended in",
            render_failure_phases,
        ),
        (
            r"fql_distill_.*\.json",
            "FQL's one-step actor against its flow on the demonstrations",
            render_fql_distill,
        ),
        (
            r"critic_bias_.*\.json",
            "Critic bias: Q on the replay data against its Monte-Carlo value",
            render_critic_bias,
        ),
        (
            r"flow_q_.*\.json",
            "Flow-Q fine-tuning against continued BC (the retired FlowQLoss)",
            render_flow_q,
        ),
    ],
    "Simulators, experts and data": [
        (r"env_throughput_.*\.json", "Environment throughput", render_env_throughput),
        (r"sampler\.json", "Replay-buffer sampling", render_sampler),
        (r"(pusht|robosuite)_experts?\.json", "Scripted experts", render_experts),
        (
            r"pusht_env\.json|robosuite_throughput_.*\.json",
            "Adapters against the raw simulator",
            render_sim_throughput,
        ),
    ],
}


def _load(path: Path) -> Any:
    return json.loads(path.read_text())


def _quick(data: Any) -> bool:
    """A --quick run's file: it checked a script, it measured nothing, so no section lists it."""
    return isinstance(data, dict) and bool(data.get("quick"))


def _link(target: Path, doc: Path) -> str:
    """``target`` as a link from the document ``doc`` (Markdown resolves links from its folder)."""
    return Path(os.path.relpath(target, doc.parent)).as_posix()


def _file_section(path: Path, data: dict, title: str, render: Callable[[dict], str], doc: Path) -> list[str]:
    try:
        body = render(data)
    except (KeyError, TypeError, ValueError) as err:  # an older layout of the file
        body = f"Not rendered: an older layout of this file ({err!r}); re-run its script."
    if isinstance(data, dict) and data.get("note"):  # a file's own words after its table, whatever renders it
        body += f"\n\n{data['note']}"
    parts = [f"### {title} (`{path.name}`)", ""]
    parts += [f"Source: [`{path.name}`]({_link(path, doc)}). Machine: {_machine(data)}.", "", body, ""]
    plot = path.with_suffix(".png")
    if plot.is_file():  # the script's own figure beside its table
        parts += [f"![{title}]({_link(plot, doc)})", ""]
    return parts


def _summary_parts(results: Path, doc: Path, level: str, overview_table: bool) -> list[str]:
    """The claims table, the overview table when asked for, and the overview figure."""
    from benchmarks import success_overview
    from benchmarks.claims import claims_table

    parts = []
    claims = claims_table(results)
    if claims:  # the digest first: each claim, its figures and a rule's verdict
        parts += [f"{level} The paper's four claims, as measured here", "", claims, ""]
    overview = success_overview.overview_table(results) if overview_table else None
    if overview:  # every task's methods side by side, before each file's own section
        parts += [f"{level} Success across tasks (the paper's Table 2 and Figure 4)", "", overview, ""]
    if (results / OVERVIEW_PLOT).is_file():
        parts += [f"![Success across tasks]({_link(results / OVERVIEW_PLOT, doc)})", ""]
    finetune = finetune_overview.overview_table(results) if overview_table else None
    if finetune:  # the headline arms of every fine-tuning start, before each file's own section
        parts += [f"{level} Fine-tuning at a glance", "", finetune, ""]
        for start, path in zip(finetune_overview.HEADLINE, finetune_overview.figure_paths(results)):
            if path.is_file():
                parts += [f"![Fine-tuning: {start}]({_link(path, doc)})", ""]
    return parts


def build_finetune_block(results: Path = RESULTS) -> str:
    """The README's fine-tuning block between its markers: the headline arms' table."""
    table = finetune_overview.overview_table(results) or "No fine-tuning results saved yet."
    return "\n".join([FT_BEGIN, "", table, "", FT_END])


def build_summary(results: Path = RESULTS, readme: Path = Path("README.md"), doc: Path = RESULTS_DOC) -> str:
    """The README's block between the markers: the claims table, the overview figure, a link to
    RESULTS.md."""
    parts = [BEGIN, "", *_summary_parts(results, readme, "###", overview_table=False)]
    parts += [f"Every figure, its source file and its machine: [{doc.name}]({_link(doc, readme)}).", "", END]
    return "\n".join(parts)


def build_results(results: Path = RESULTS, doc: Path = RESULTS_DOC) -> str:
    """The whole of RESULTS.md: the summary, then every results file's section in its group."""
    from benchmarks.defaults_evidence import evidence_table

    files = [(p, _load(p)) for p in sorted(results.glob("*.json"))]
    files = [(p, d) for p, d in files if not _quick(d)]
    sections: dict[str, list[str]] = {group: [] for group in GROUPS}
    rendered = set()
    for group, renderers in GROUPS.items():
        for pattern, title, render in renderers:
            for path, data in files:
                if path.name not in rendered and re.fullmatch(pattern, path.name):
                    rendered.add(path.name)
                    sections[group] += _file_section(path, data, title, render, doc)
    heading = "# Results"
    parts = [
        heading,
        "",
        f"Generated by `python -m benchmarks.report` from the JSON files under `{results.as_posix()}/`: no "
        "number here is typed by hand, and `python -m benchmarks.report --check` (run in CI) fails, naming "
        "the section, when this file differs from what those files give. Each section's heading names its "
        "source file. The scripts that write them: [docs/benchmarks.md](../docs/benchmarks.md).",
        "",
        "## Summary",
        "",
        *_summary_parts(results, doc, "###", overview_table=True),
    ]
    for group, section in sections.items():
        if section:
            parts += [f"## {group}", "", *section]
    evidence = evidence_table(results)
    if evidence:
        parts += ["## Defaults and the measurements behind them", "", evidence, ""]
    unrendered = [p.name for p, _ in files if p.name not in rendered]
    if unrendered:
        parts += ["## Other saved results", ""]
        parts += ["No renderer yet: " + ", ".join(f"`{n}`" for n in unrendered) + ".", ""]
    return "\n".join(parts).rstrip("\n") + "\n"


def _sections(text: str) -> dict[str, str]:
    """Markdown text by heading ("(top)" before the first): the unit --check names."""
    found: dict[str, list[str]] = {"(top)": []}
    current = "(top)"
    for line in text.splitlines():
        if line.startswith("#"):
            current = line.lstrip("#").strip()
            found.setdefault(current, [])
        found[current].append(line)
    return {k: "\n".join(v) for k, v in found.items()}


def stale_sections(old: str, new: str) -> list[str]:
    """Headings whose text differs between ``old`` and ``new``, or that only one of them has."""
    a, b = _sections(old), _sections(new)
    names = list(b) + [k for k in a if k not in b]
    stale = [k for k in names if a.get(k) != b.get(k)]
    if not stale and old != new:  # same sections, different order
        stale = ["(the order of the sections)"]
    return stale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--readme", default="README.md")
    parser.add_argument("--results", default=str(RESULTS), help="the folder of saved JSON")
    parser.add_argument("--out", default=str(RESULTS_DOC), help="the generated results document")
    parser.add_argument(
        "--check", action="store_true", help="exit 1 when RESULTS.md or the README's summary differs"
    )
    args = parser.parse_args(argv)
    readme, results, out = Path(args.readme), Path(args.results), Path(args.out)
    text = readme.read_text()
    if BEGIN not in text or END not in text:
        print(f"{readme}: no results markers ({BEGIN} ... {END}); add them where the summary goes")
        return 2
    if not args.check:  # the figure is drawn from the same files; --check only reads
        from benchmarks.success_overview import overview_figure

        overview_figure(results, results / OVERVIEW_PLOT)
        finetune_overview.overview_figures(results)
    summary = build_summary(results, readme, out)
    blocks = [(BEGIN, END, summary, "the results summary")]
    if FT_BEGIN in text and FT_END in text:
        blocks.append((FT_BEGIN, FT_END, build_finetune_block(results), "the fine-tuning table"))
    new_readme, stale_blocks = text, []
    for begin, end, block, what in blocks:
        old_block = new_readme[new_readme.index(begin) : new_readme.index(end) + len(end)]
        if old_block != block:
            stale_blocks.append(what)
        new_readme = new_readme.replace(old_block, block)
    new_doc = build_results(results, out)
    if args.check:
        problems = [f"{readme}: {what} between the markers is out of date" for what in stale_blocks]
        if not out.is_file():
            problems.append(f"{out}: missing")
        elif stale := stale_sections(out.read_text(), new_doc):
            problems.append(f"{out}: out of date in " + "; ".join(f"'{s}'" for s in stale))
        for problem in problems:
            print(problem)
        if problems:
            print("run python -m benchmarks.report to rebuild them from the saved JSON")
        return 1 if problems else 0
    readme.write_text(new_readme)
    out.write_text(new_doc)
    print(f"{out} and the summary in {readme} rebuilt from {results}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
