"""The RESULTS.md sections of fine-tuning: ``finetune_cost_*.json`` (``bench_finetune_cost``): where a
QC / FQL / DSRL update's time goes, and env steps/s with each algorithm's acting module;
``finetune_online_*.json`` (``bench_finetune_online``): success against env steps per algorithm beside
the control arms.

For ``benchmarks.report``'s ``GROUPS["Fine-tuning"]``, the entry
``(r"finetune_cost_.*\\.json", "Fine-tuning: cost of an update and of acting", render_finetune_cost)``.
"""

from __future__ import annotations

__all__ = ["render_finetune_cost", "render_finetune_online"]

#: the parts of an update the bench times, in the table's column order
_PARTS = ("update", "targets", "proposals_2nfe", "critic_fwd_bwd", "actor_fwd_bwd", "bc_fwd_bwd")


def _ms(value: float | None) -> str:
    return "–" if value is None else (f"{value:,.0f}" if value >= 1000 else f"{value:.3g}")


def render_finetune_cost(data: dict) -> str:
    lines = [
        f"Task {data['task']}, batch {data['batch']}, UNet {data['policy_down_dims']}, median wall ms of "
        f"{data['rounds']} rounds per part of one update (a part's share can exceed the update's: each is "
        "timed alone).",
        "",
        "| setting | " + " | ".join(_PARTS) + " | updates/s |",
        "|---|" + "---|" * (len(_PARTS) + 1),
    ]
    for name, parts in data["wall_ms"].items():
        cells = " | ".join(_ms(parts.get(p)) for p in _PARTS)
        lines.append(f"| {name} | {cells} | {data['updates_per_s'][name]:.3g} |")
    env = data["env"]
    lines += [
        "",
        f"Acting ({env['setting']}): raw simulator {env['raw_steps_per_s']:.4g} steps/s.",
        "",
        "| acting module | steps/s | × raw |",
        "|---|---|---|",
    ]
    lines += [
        f"| {name} | {a['steps_per_s']:.4g} | {a['over_raw']:.2f} |" for name, a in env["adapters"].items()
    ]
    design = data.get("design") or {}
    if design:
        lines += ["", "What each figure decided:", ""]
        lines += [f"- `{key}`: {text}" for key, text in design.items()]
    return "\n".join(lines)


def _rate(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def _mean(values: list[float]) -> str:
    return f"{sum(values) / len(values):.3g}" if values else "–"


def render_finetune_online(data: dict) -> str:
    lines = [
        f"Task {data['task']}, from `{data['checkpoint']}`; validation {data['val_episodes']} episodes every "
        f"{data['eval_every']:,} env steps, test {data['test_episodes']} episodes of the best-validated "
        "policy (the start competes, so no reported policy is below its own validation).",
        "",
        "| arm | seeds | test success_once (mean, min-max) | validation at env steps (mean) | "
        "env steps/s acting | updates/s |",
        "|---|---|---|---|---|---|",
    ]
    for name, control in data["controls"].items():
        test = control["test"]
        lines.append(
            f"| {name} | 1 | {_rate(test['success_once'])} ({test['episodes']} episodes) | – | – | – |"
        )
    for name, algo in data["algorithms"].items():
        agg = algo["aggregate"]
        runs = list(algo["runs"].values())
        curve = ", ".join(f"{c['env_steps'] // 1000}k: {c['mean']:.2f}" for c in agg["curve"])
        speed = [r["env_steps_per_s_actor"] for r in runs if r.get("env_steps_per_s_actor")]
        ups = [r["updates_per_s"] for r in runs if r.get("updates_per_s")]
        early = " (stopped early)" if any(r["stopped_early"] for r in runs) else ""
        lines.append(
            f"| {name}{early} | {len(runs)} | {_rate(agg['test_mean'])} ({_rate(agg['test_min'])}-"
            f"{_rate(agg['test_max'])}) | {curve} | "
            f"{_mean(speed)} | {_mean(ups)} |"
        )
    overrides = {a: v["budget_overrides"] for a, v in data["algorithms"].items() if v["budget_overrides"]}
    if overrides:
        lines += [
            "",
            "Budget overrides of the presets: "
            + "; ".join(f"{a}: `{' '.join(o)}`" for a, o in overrides.items()),
        ]
    return "\n".join(lines)
