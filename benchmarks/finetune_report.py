"""The RESULTS.md section of ``finetune_cost_*.json`` (``bench_finetune_cost``): where a QC / FQL / DSRL
update's time goes, and env steps/s with each algorithm's acting module.

For ``benchmarks.report``'s ``GROUPS["Fine-tuning"]``, the entry
``(r"finetune_cost_.*\\.json", "Fine-tuning: cost of an update and of acting", render_finetune_cost)``.
"""

from __future__ import annotations

__all__ = ["render_finetune_cost"]

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
