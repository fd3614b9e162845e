"""The RESULTS.md sections of fine-tuning (``benchmarks/finetune/``): ``finetune_cost_*.json``
(``bench_finetune_cost``): where a QC / FQL / DSRL update's time goes, and env steps/s with each
algorithm's acting module; ``noise_authority*.json`` (``bench_noise_authority``): how far a steering
policy's input noise moves each checkpoint's executed actions; ``critic_bias_*.json``
(``bench_critic_bias``): the critics' value of a run's replay data against its Monte-Carlo value, per
critic setting. :func:`render_finetune_online` is one ``finetune_online_*.json`` file's own table, which
``bench_finetune_online`` prints; RESULTS.md shows every such file's arms in one table
(:mod:`benchmarks.report.finetune_overview`).
"""

from __future__ import annotations

__all__ = [
    "render_critic_bias",
    "render_finetune_cost",
    "render_finetune_online",
    "render_noise_authorities",
    "render_noise_authority",
    "render_reinflow_cost",
]

#: the parts of an update the bench times, in the table's column order
_PARTS = ("update", "targets", "proposals_2nfe", "critic_fwd_bwd", "actor_fwd_bwd", "bc_fwd_bwd")


def _ms(value: float | None) -> str:
    return "–" if value is None else (f"{value:,.0f}" if value >= 1000 else f"{value:.3g}")


def _network(data: dict) -> str:
    """The policy network a cost file measured (older files record the UNet's down_dims only)."""
    if "network" not in data:
        return f"UNet {data['policy_down_dims']}"
    return f"{'UNet' if data['network'] == 'unet' else 'MLP'} {data['network_dims']}"


def render_finetune_cost(files: list[tuple[str, dict]]) -> str:
    """One table of every network's settings at one torch thread, then acting against the raw
    simulator, then what each figure decided. A file measured at more threads (same network) adds a
    column of its whole-update time and of its acting rate, rather than repeating every row."""
    base = [d for _, d in files if d.get("threads", 1) == 1]
    more = {}  # network -> {threads: data}
    for _, d in files:
        if d.get("threads", 1) != 1:
            more.setdefault(_network(d), {})[d["threads"]] = d
    extra = sorted({t for by_threads in more.values() for t in by_threads})
    first = base[0]
    lines = [
        f"Task {first['task']}, batch {first['batch']}, median wall ms per part of one update at one torch "
        "thread over "
        + ", ".join(f"{d['rounds']} rounds ({_network(d)})" for d in base)
        + " (a part's share can exceed the update's: each is timed alone)"
        + "".join(f"; `update, {t} thr.`: the whole update at {t} threads" for t in extra)
        + ".",
        "",
        "| policy network | setting | "
        + " | ".join(_PARTS)
        + "".join(f" | update, {t} thr." for t in extra)
        + " | updates/s |",
        "|---|---|" + "---|" * (len(_PARTS) + len(extra) + 1),
    ]

    def fmt(value: float | None) -> str:
        return "–" if value is None else f"{value:.4g}"

    def others(data: dict) -> list[dict | None]:
        """The same network's files at the extra thread counts (None where not measured)."""
        return [more.get(_network(data), {}).get(t) for t in extra]

    for data in base:
        at_threads = others(data)
        for name, parts in data["wall_ms"].items():
            cells = " | ".join(_ms(parts.get(p)) for p in _PARTS)
            cells += "".join(f" | {_ms(o and o['wall_ms'].get(name, {}).get('update'))}" for o in at_threads)
            lines.append(f"| {_network(data)} | {name} | {cells} | {data['updates_per_s'][name]:.3g} |")
    lines += [
        "",
        "| policy network | acting module | steps/s | × raw |"
        + "".join(f" steps/s, {t} thr. |" for t in extra),
        "|---|---|---|---|" + "---|" * len(extra),
    ]
    for data in base:
        env = data["env"]
        at_threads = others(data)
        lines.append(
            f"| {_network(data)} | raw simulator ({env['setting']}) | {env['raw_steps_per_s']:.4g} | 1 |"
            + "".join(f" {fmt(o and o['env']['raw_steps_per_s'])} |" for o in at_threads)
        )
        lines += [
            f"| {_network(data)} | {name} | {a['steps_per_s']:.4g} | {a['over_raw']:.2f} |"
            + "".join(
                f" {fmt(o and o['env']['adapters'].get(name, {}).get('steps_per_s'))} |" for o in at_threads
            )
            for name, a in env["adapters"].items()
        ]
    design = [(data, key, text) for data in base for key, text in (data.get("design") or {}).items()]
    if design:
        lines += ["", "What each figure decided:", ""]
        lines += [f"- {_network(data)}, `{key}`: {text}" for data, key, text in design]
    return "\n".join(lines)


def _rate(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def _mean(values: list[float]) -> str:
    return f"{sum(values) / len(values):.3g}" if values else "–"


def _control_curve(runs) -> str:
    """A seeded control's validation (mean over seeds) at each of its update counts: its runs record
    their validations in the test's selection (no env steps: the column says updates)."""
    per_step: dict[int, list[float]] = {}
    for run in runs:
        for e in (run["test"].get("selection") or {}).get("evaluations", []):
            per_step.setdefault(int(e["step"]), []).append(float(e["success_once"]))
    if not per_step:
        return "–"
    # seeds validated at other counts (a run lengthened on resume) show apart, with how many read each
    return ", ".join(
        f"{k:,} upd.: {sum(v) / len(v):.2f}" + ("" if len(v) == len(runs) else f" ({len(v)} of {len(runs)})")
        for k, v in sorted(per_step.items())
    )


def _data_cost(runs) -> str:
    """What the arm's data cost in the simulator beyond the start's demonstrations (shifted replays),
    as the first run records it (every seed trains on the same file)."""
    cost = next((r.get("data_cost") for r in runs if r.get("data_cost")), None)
    if not cost:
        return ""
    return (
        f"; its data: {cost['attempts']} shifted replays, {cost['successes']} kept, "
        f"{cost['env_steps']:,} env steps"
    )


def render_finetune_online(data: dict) -> str:
    lines = [
        f"Task {data['task']}, from `{data['checkpoint']}`; validation {data['val_episodes']} episodes every "
        f"{data['eval_every']:,} env steps, test {data['test_episodes']} episodes of the best-validated "
        "policy (the start is kept unless a model validates more than one standard error above it).",
        "",
        "| arm | seeds | test success_once (mean, min-max) | validation at env steps (mean) | "
        "env steps/s acting | updates/s |",
        "|---|---|---|---|---|---|",
    ]
    for name, control in data["controls"].items():
        test = control["test"]
        if "seeds" in control:  # a control run once per seed (bench_finetune_online's continued BC)
            updates = f", {control['updates']:,} updates" if control.get("updates") else ""
            if control.get("overrides"):
                updates += ", " + " ".join(f"`{o}`" for o in control["overrides"])
            updates += _data_cost(control["seeds"].values())
            lines.append(
                f"| {name}{updates} | {len(control['seeds'])} | {_rate(test['success_once'])} "
                f"({_rate(test['min'])}-{_rate(test['max'])}; {test['episodes']} episodes) | "
                f"{_control_curve(control['seeds'].values())} | – | – |"
            )
            continue
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
        early += _data_cost(runs)
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


#: the action-dim groups of ``bench_noise_authority.action_groups``, in the table's column order
_GROUPS = ("position", "rotation", "gripper")


def _group_mean(values: list[float], dims: list[int] | None) -> str:
    return f"{sum(values[d] for d in dims) / len(dims):.3g}" if dims else "–"


def render_noise_authorities(files: list[tuple[str, dict]]) -> str:
    """Every file's checkpoints in one table; the files must share the draws they were measured with."""
    first = files[0][1]
    keys = ("states", "draws", "seed", "bound")
    for name, data in files[1:]:
        if any(data[k] != first[k] for k in keys):
            raise ValueError(
                f"{name}: measured with other {keys} than {files[0][0]}: one table cannot hold both"
            )
    checkpoints = {k: v for _, data in files for k, v in data["checkpoints"].items()}
    return render_noise_authority({**first, "checkpoints": checkpoints})


def render_noise_authority(data: dict) -> str:
    checkpoints = data["checkpoints"].values()
    groups = [g for g in _GROUPS if any(g in c["dim_groups"] for c in checkpoints)]
    header = ["checkpoint", "task", "method, sampler (NFE)"]
    header += [f"{g} authority" for g in groups] + [f"{g} std over noise (norm.)" for g in groups]
    header += ["all dims, std (norm.): corners / N(0, 9)"]
    lines = [
        f"{data['states']} states per checkpoint (windows of its training demonstrations, seed "
        f"{data['seed']}), {data['draws']} noise draws per state, executed steps only. Authority: the std "
        f"of the executed actions over w ~ N(0, I) clipped to ±{data['bound']:g} divided by their std "
        "across states (at w = 0), averaged over a group's dims; std over noise in the policy's normalised "
        "action units (limits: each dim spans [-1, 1] over the demonstrations).",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
    ]
    for name, c in data["checkpoints"].items():
        norm, dims = c["normalized"], c["dim_groups"]
        every = list(range(c["action_dim"]))
        sampler = c["sampler"]
        cells = [name, c["task"], f"{c['method']}, {sampler['name']} ({sampler['nfe']})"]
        cells += [_group_mean(c["authority"], dims.get(g)) for g in groups]
        cells += [_group_mean(norm["std_noise"], dims.get(g)) for g in groups]
        cells.append(
            f"{_group_mean(norm['std_noise_corners'], every)} / {_group_mean(norm['std_noise_wide'], every)}"
        )
        lines.append("| " + " | ".join(cells) + " |")
    stepped = [n for n, c in data["checkpoints"].items() if c["sampler"].get("per_step_noise")]
    lines += [
        "",
        "A DSRL actor, which acts only through w within the bound, can move a policy's executed actions "
        "by about its std over noise, that is by the authority's fraction of how much they vary from state "
        "to state: where the authority is a few percent, its critic sees a Q nearly flat in w and little "
        "behaviour is within its reach.",
    ]
    if stepped:
        lines += [
            "",
            f"{', '.join(stepped)}: the sampler draws noise at every step; it is held fixed across w (only "
            "the initial noise is steered) and its own spread is the file's `std_step_noise`.",
        ]
    return "\n".join(lines)


def _spread(stat: dict) -> str:
    return f"{stat['mean']:.2f} ({stat['min']:.2f}, {stat['max']:.2f})"


def render_critic_bias(data: dict) -> str:
    y = data["yardstick"]
    points = data["report_at"]
    last_point = points[-1]
    seeds = data["seeds"]
    lines = [
        f"Run `{data['run']}` ({data['task']}, {data['algorithm']}): its online buffer `{data['dump']}` "
        f"({data['env_steps']:,} env steps) replayed offline by a fresh loss per setting, "
        f"{data['updates']:,} updates at batch {data['batch_size']}, seeds {', '.join(map(str, seeds))}. "
        "Q_data: the critics' mean value of the batch's windows at that update (0: the fresh critics), "
        "mean over seeds (min, max). The yardstick, the windows' Monte-Carlo value (the "
        f"{y['reward']} reward discounted to the episode's end, gamma {y['gamma']:g}), is "
        f"**{y['mc_mean']:.3f}** over {y['windows']:,} windows of {y['episodes']:,} episodes; "
        f"{y['truncated_fraction']:.0%} of them lie in episodes that ended truncated (their tail counts 0: "
        f"a lower bound), {y['success_fraction']:.0%} in episodes that succeeded.",
        "",
        "| setting | critics | "
        + " | ".join(f"Q_data @{p:,}" for p in points)
        + f" | target @{last_point:,} | Q_actor @{last_point:,} | s/update |",
        "|---|---|" + "---|" * (len(points) + 3),
    ]
    for name, c in data["configs"].items():
        by_update = {row["update"]: row for row in c["mean"]}
        last = by_update.get(last_point, {})
        s = c["settings"]
        drawn = f", min of {s['target_critics']} drawn" if s["target_critics"] else f", {s['q_agg']}"
        critics = f"{s['num_critics']} x {'x'.join(map(str, s['critic_hidden_dims']))}{drawn}"
        cells = [_spread(by_update[p]["q_data_mean"]) if p in by_update else "–" for p in points]
        cells += [_spread(last[k]) if k in last else "–" for k in ("target_mean", "q_actor_mean")]
        cells.append(f"{last['s_per_update']['mean']:.3g}" if last else "–")
        own = f" (yardstick {c['yardstick']['mc_mean']:.3f})" if c.get("yardstick") else ""
        runs = f" ({len(c['seeds'])} of {len(seeds)} seeds)" if len(c["seeds"]) < len(seeds) else ""
        lines.append(f"| {name}{own}{runs} | {critics} | " + " | ".join(cells) + " |")
    if not data.get("finished", True):
        lines += ["", "The file is partial: its script was still running (or stopped) when it was saved."]
    return "\n".join(lines)


def render_reinflow_cost(data: dict) -> str:
    """``bench_reinflow_cost``: what PPO over the noisy 2-NFE chain would cost, per million env steps."""
    ms, per = data["wall_ms"], data["core_hours_per_million_env_steps"]
    env = data["env"]
    n = data["envs"]
    lines = [
        f"{data['task']}, {_network(data)} policy, one torch thread; PPO minibatch of {data['batch']} "
        f"chains, {data['epochs']} epochs over every chunk decision ({data['executed_per_chunk']} "
        "executed actions).",
        "",
        "| figure | value |",
        "|---|---|",
        f"| 2-NFE chunk / noisy chain, batch 1 (ms) | {ms['chunk_2nfe_b1']:.3g} / {ms['chain_b1']:.3g} |",
        f"| 2-NFE chunk / noisy chain, batch {n} (ms) | {ms[f'chunk_2nfe_b{n}']:.3g} / "
        f"{ms[f'chain_b{n}']:.3g} |",
        f"| PPO minibatch: chain log-likelihood, value MLP, backward, Adam (ms) | "
        f"{ms['ppo_minibatch']:.3g} |",
        f"| raw env steps/s: in this process / {n} worker processes | "
        f"{env['in_process']['raw_steps_per_s']:.0f} / {env['workers']['raw_steps_per_s']:.0f} |",
        f"| core-hours per million env steps: env / acting / PPO / total | {per['env']:.2f} / "
        f"{per['acting']:.2f} / {per['ppo']:.2f} / {per['total']:.2f} |",
        f"| env steps in 2 hours of 2 cores, at most | {data['env_steps_in_2h_of_2_cores_at_most']:,} |",
    ]
    published = data["hours_of_2_cores_for_published"]
    lines += [
        "",
        "At this rate ReinFlow's published budgets take "
        + ", ".join(
            f"{k.replace('_', ' ')} {data['published_env_steps'][k] / 1e6:g}M env steps: {v:g} h"
            for k, v in published.items()
        )
        + " of 2 cores. The simulator, not the policy, sets the cost.",
    ]
    return "\n".join(lines)
