"""PushT's two ways around the T, per policy: how often a trained policy commits to going around the
block on the left or on the right, against reaching it straight between the two (what averaging
the two routes gives), beside its Diffusion Policy score and success.

On the Diffusion Policy test seeds (``eval.protocol=diffusion_policy``: 50 seeds from 100000, 300
steps), the scripted expert runs first. The *bimodal starts* are the seeds where its first way to
the block went around it by free choice (both sides viable, its per-episode draw decided; see
``PushTPlanner.path``). Then each policy runs on the same seeds through ``make_env`` and its actor,
and every episode's first approach, the expert's included, is labelled by one rule computed from
gym-pusht's state (:mod:`l1flow_rl.experts.pusht.routes`: the agent's net angle swept around the
T's centre until it first touches the block; ``left``/``right`` beyond +-90 degrees, ``between``
inside, ``no_contact``). The rule is checked against the planner's own labels on the bimodal seeds
(``expert.agreement_on_bimodal``).

Per policy: score (mean of each episode's best clip(coverage / 0.95, 0, 1), Student-t 95 %
interval), success (coverage > 0.95 at any step, Wilson 95 %), and route shares (Wilson 95 % each)
on all seeds and on the bimodal seeds. Prints a table, saves ``benchmarks/results/pusht_modes.json``
and a PNG of the agent's paths on a few bimodal seeds. Rollouts run on the CPU (policy noise seeded
from the first seed, as ``l1flow-rl eval`` does).

    python -m benchmarks.success.bench_pusht_modes --runs runs/pusht_l1flow runs/pusht_flow runs/pusht_reg
    python -m benchmarks.success.bench_pusht_modes --checkpoints l1flow=A.pt flow=B.pt regression=C.pt
    python -m benchmarks.success.bench_pusht_modes --quick --checkpoints tiny=runs/x/checkpoints/latest.pt

A run directory's checkpoint is the one its eval.json reports: ``checkpoints/best.pt`` (written when
the run evaluated), else ``checkpoints/latest.pt``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from l1flow_rl.envs.pusht.geometry import BLOCK_COG, GOAL_POSE, T_CORNERS, to_world

from benchmarks.lib.common import format_table, machine_info, parse_args, save_results
from l1flow_rl.evaluation.metrics import MEAN, RATE, summarize_metrics, wilson_interval
from l1flow_rl.experts.pusht.routes import CONTACT_PX, ROUTES, classify_approach, sim_states

__all__ = ["main", "parse_policies", "route_shares", "run_checkpoint"]

PROTOCOL = "diffusion_policy"


# -- which checkpoints ------------------------------------------------------------------------------


def run_checkpoint(run_dir: Path) -> Path:
    """The checkpoint a training run reports in its eval.json: best.pt, else latest.pt."""
    for name in ("best.pt", "latest.pt"):
        path = run_dir / "checkpoints" / name
        if path.is_file():
            return path
    raise FileNotFoundError(f"run {str(run_dir)!r} has neither checkpoints/best.pt nor checkpoints/latest.pt")


def _run_name(run_dir: Path) -> str:
    summary = run_dir / "summary.json"
    if summary.is_file():
        return str(json.loads(summary.read_text()).get("policy") or run_dir.name)
    return run_dir.name


def parse_policies(checkpoints: Sequence[str], runs: Sequence[Path]) -> dict[str, Path]:
    """``NAME=PATH`` checkpoints and run directories (named by their summary.json's policy) -> paths."""
    named: list[tuple[str, Path]] = []
    for item in checkpoints:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"--checkpoints takes NAME=PATH, got {item!r}")
        named.append((name, Path(path)))
    named += [(_run_name(r), run_checkpoint(r)) for r in runs]
    if not named:
        raise ValueError("pass --checkpoints NAME=PATH ... or --runs RUN_DIR ...")
    names = [n for n, _ in named]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise ValueError(f"policy names {duplicates} appear twice; name them with --checkpoints NAME=PATH")
    missing = [str(p) for _, p in named if not p.is_file()]
    if missing:
        raise FileNotFoundError(f"checkpoints not found: {missing}")
    return dict(named)


# -- summaries ----------------------------------------------------------------------------------------


def route_shares(routes: Sequence[str]) -> dict[str, Any]:
    """Counts, shares and Wilson 95 % intervals of each route among ``routes``."""
    n = len(routes)
    counts = {r: routes.count(r) for r in ROUTES}
    return {
        "n": n,
        "counts": counts,
        "shares": {r: (c / n if n else None) for r, c in counts.items()},
        "ci95": {r: (list(wilson_interval(c, n)) if n else None) for r, c in counts.items()},
    }


def _outcome(episodes: Sequence[Mapping[str, Any]], bimodal: set[int]) -> dict[str, Any]:
    stats = summarize_metrics(episodes, {"score": MEAN, "success": RATE})
    return {
        "episodes": len(episodes),
        "score": stats["score"]["mean"],
        "success": stats["success"]["mean"],
        "ci95": {k: [stats[k]["ci95_low"], stats[k]["ci95_high"]] for k in ("score", "success")},
        "routes_all": route_shares([e["route"] for e in episodes]),
        "routes_bimodal": route_shares([e["route"] for e in episodes if e["seed"] in bimodal]),
    }


def _approach(seed: int, states: np.ndarray, args: argparse.Namespace) -> dict[str, Any]:
    a = classify_approach(
        states[:, :2],
        states[:, 2:5],
        threshold=math.radians(args.sweep_threshold_deg),
        contact_px=args.contact_px,
    )
    return {
        "seed": seed,
        "route": a.route,
        "sweep_deg": round(math.degrees(a.sweep), 1),
        "start_step": a.start_step,
        "contact_step": a.contact_step,
    }


# -- the expert -----------------------------------------------------------------------------------------


def expert_routes(
    seeds: Sequence[int], args: argparse.Namespace
) -> tuple[list[dict[str, Any]], dict[int, np.ndarray]]:
    """The planner on ``seeds``: per seed its first route (as planned and as the rule labels it)."""
    from l1flow_rl.experts.pusht.demos import run_episodes

    episodes, paths = [], {}
    for seed, demo, error in run_episodes(
        seeds, max_steps=args.max_steps, workers=args.workers, progress=not args.quiet, desc="PushT expert"
    ):
        if demo is None:
            episodes.append({"seed": seed, "error": error or "no reproducible start"})
            continue
        states = demo.arrays["state"].astype(np.float64)  # the state before each action
        paths[seed] = states
        episodes.append(
            {
                **_approach(seed, states, args),
                "planned_side": demo.first_side,
                "free_choice": demo.first_chosen,
                "score": demo.score,
                "success": bool(demo.success),
                "steps": demo.steps,
            }
        )
    return episodes, paths


def _expert_record(episodes: list[dict[str, Any]], bimodal: set[int]) -> dict[str, Any]:
    ran = [e for e in episodes if "error" not in e]
    free = [e for e in ran if e["seed"] in bimodal]
    agree = sum(e["route"] == e["planned_side"] for e in free)
    confusion = {
        side: {r: sum(e["route"] == r for e in ran if e["planned_side"] == side) for r in ROUTES}
        for side in ("left", "right", "none")
    }
    return {
        **_outcome(ran, bimodal),
        "errors": {str(e["seed"]): e["error"] for e in episodes if "error" in e},
        "bimodal_seeds": sorted(bimodal),
        "planned_side_on_bimodal": {s: sum(e["planned_side"] == s for e in free) for s in ("left", "right")},
        "agreement_on_bimodal": agree / len(free) if free else None,
        "agreement_ci95": list(wilson_interval(agree, len(free))) if free else None,
        # rows: the planner's first path (left/right around the block, none: straight); columns: the rule
        "confusion_planned_vs_rule": confusion,
        "per_episode": episodes,
    }


# -- the policies ------------------------------------------------------------------------------------


def rollout(actor, task, seeds: Sequence[int], args: argparse.Namespace, obs_horizon: int) -> list[dict]:
    """Run ``actor`` from each seed for ``task.max_episode_steps`` steps (``args.num_envs`` envs in this
    process); per episode its score, success and gym-pusht states [T + 1, 5] (start included)."""
    from l1flow_rl.envs import make_env
    from l1flow_rl.envs.per_env import seeded_reset
    from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
    from torchrl.modules import MultiStepActorWrapper

    n = max(1, min(args.num_envs, len(seeds)))
    env = make_env(task, num_envs=n, device="cpu", obs_horizon=obs_horizon, render=False, backend="serial")
    executor = MultiStepActorWrapper(actor, n_steps=int(actor.policy.action_steps), init_key="is_init")
    exploration = ExplorationType.DETERMINISTIC if args.deterministic else ExplorationType.RANDOM
    out = []
    try:
        with torch.random.fork_rng(), torch.no_grad(), set_exploration_type(exploration):
            torch.manual_seed(seeds[0])
            for i in range(0, len(seeds), n):
                batch = list(seeds[i : i + n])
                td = seeded_reset(env, None, batch + [batch[-1]] * (n - len(batch)))  # pad the last batch
                frames, rewards, success = [td["observation"][:, -1]], [], []
                for _ in range(int(task.max_episode_steps)):
                    td = env.step(executor(td))
                    frames.append(td["next", "observation"][:, -1])
                    rewards.append(td["next", "reward"].reshape(n))
                    success.append(td["next", "success"].reshape(n))
                    td = step_mdp(td)
                states = sim_states(torch.stack(frames, 1).numpy(), task.obs_mode)
                rewards_np, success_np = torch.stack(rewards, 1).numpy(), torch.stack(success, 1).numpy()
                for j, seed in enumerate(batch):
                    out.append(
                        {
                            "seed": seed,
                            "score": float(rewards_np[j].max()),  # the evaluator's ("max", "reward")
                            "success": bool(success_np[j].any()),  # success_once
                            "states": states[j],
                        }
                    )
    finally:
        env.close()
    return out


def policy_routes(
    path: Path, seeds: Sequence[int], args: argparse.Namespace
) -> tuple[dict[str, Any], dict[int, np.ndarray]]:
    """Roll the checkpoint at ``path`` out on ``seeds`` under the protocol; label each episode's route."""
    from l1flow_rl.evaluation.evaluator import sampler_record
    from l1flow_rl.evaluation.plan import task_from
    from l1flow_rl.evaluation.protocols import get_protocol
    from l1flow_rl.workspace.checkpoint import load_actor

    actor, cfg = load_actor(path, use_ema=True, map_location="cpu")
    task = get_protocol(PROTOCOL).eval_task(task_from(cfg.task))
    task = dataclasses.replace(task, max_episode_steps=args.max_steps)
    start = time.perf_counter()
    episodes = rollout(actor, task, seeds, args, int(cfg.policy.obs_horizon))
    paths = {e["seed"]: e.pop("states") for e in episodes}
    for e in episodes:
        e.update(_approach(e["seed"], paths[e["seed"]], args))
    record = {
        "checkpoint": str(path),
        "policy": str(cfg.policy.name),
        "task": task.name,
        "obs_mode": task.obs_mode,
        "sampler": sampler_record(actor),
        "rollout_seconds": round(time.perf_counter() - start, 1),
        "per_episode": episodes,
    }
    return record, paths


# -- output --------------------------------------------------------------------------------------------


def _row(name: str, block: Mapping[str, Any]) -> dict[str, Any]:
    def share(where: str, route: str) -> str:
        routes = block[where]
        value = routes["shares"][route]
        return "-" if value is None else f"{value:.2f} ({routes['counts'][route]}/{routes['n']})"

    def interval(metric: str) -> str:
        low, high = block["ci95"][metric]
        return f"{block[metric]:.3f}" + ("" if low is None else f" [{low:.2f}, {high:.2f}]")

    return {
        "policy": name,
        "score": interval("score"),
        "success": interval("success"),
        **{f"{r} (bimodal)": share("routes_bimodal", r) for r in ROUTES},
        "between (all)": share("routes_all", "between"),
    }


def _plot(
    paths: Mapping[str, Mapping[int, np.ndarray]],
    approaches: Mapping[str, Mapping[int, Mapping[str, Any]]],
    seeds: Sequence[int],
    out: Path,
) -> Path:
    """The agent's path until first contact (dots after it: the next 20 steps) per policy, per seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    fig, axes = plt.subplots(1, len(seeds), figsize=(4 * len(seeds), 4.2), squeeze=False)
    for ax, seed in zip(axes[0], seeds):
        ax.add_patch(Polygon(to_world(T_CORNERS, GOAL_POSE), fill=False, ls="--", ec="0.4", lw=1))
        for i, (name, by_seed) in enumerate(paths.items()):
            states = by_seed.get(seed)
            if states is None:
                continue
            if i == 0:
                ax.add_patch(Polygon(to_world(T_CORNERS, states[0, 2:5]), fc="lightgray", ec="gray"))
                centre = to_world(BLOCK_COG[None], states[0, 2:5])[0]
                ax.plot(*centre, "k+")
            a = approaches[name][seed]
            end = len(states) if a["contact_step"] is None else a["contact_step"] + 1
            (line,) = ax.plot(states[:end, 0], states[:end, 1], "-", lw=1.5, label=f"{name}: {a['route']}")
            ax.plot(states[end - 1 : end + 20, 0], states[end - 1 : end + 20, 1], ":", color=line.get_color())
            ax.plot(states[0, 0], states[0, 1], "o", color=line.get_color(), ms=4)
        ax.set_xlim(0, 512)
        ax.set_ylim(512, 0)  # image coordinates, as gym-pusht renders
        ax.set_aspect("equal")
        ax.set_title(f"seed {seed}", fontsize=9)
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    from l1flow_rl.evaluation.protocols import get_protocol

    protocol = get_protocol(PROTOCOL)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoints", nargs="*", default=[], metavar="NAME=PATH")
    parser.add_argument("--runs", nargs="*", default=[], type=Path, metavar="RUN_DIR")
    parser.add_argument("--episodes", type=int, default=protocol.episodes, help="test seeds (protocol: 50)")
    parser.add_argument("--first-seed", type=int, default=protocol.seed, help="(protocol: 100000)")
    parser.add_argument("--max-steps", type=int, default=300, help="episode length (protocol: 300)")
    parser.add_argument("--num-envs", type=int, default=10, help="policy envs stepped together")
    parser.add_argument("--workers", type=int, default=2, help="expert worker processes")
    parser.add_argument("--deterministic", action="store_true", help="sample chunks from zero noise")
    parser.add_argument("--sweep-threshold-deg", type=float, default=90.0)
    parser.add_argument("--contact-px", type=float, default=CONTACT_PX)
    parser.add_argument("--plot-seeds", type=int, default=3, help="bimodal seeds drawn in the PNG (0: none)")
    parser.add_argument("--out", default="benchmarks/results/pusht_modes.json")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument(
        "--quick", action="store_true", help="2 seeds, 60 steps: checks the script, not the claim"
    )
    args = parse_args(parser, argv)
    if args.quick:
        args.episodes, args.max_steps, args.num_envs, args.workers = min(args.episodes, 2), 60, 2, 1
    if args.episodes < 1 or args.max_steps < 1:
        parser.error(f"--episodes and --max-steps must be >= 1, got {args.episodes} and {args.max_steps}")
    try:
        policies = parse_policies(args.checkpoints, args.runs)
    except (ValueError, FileNotFoundError) as err:
        parser.error(str(err))
    seeds = list(range(args.first_seed, args.first_seed + args.episodes))
    start = time.perf_counter()

    expert_episodes, expert_paths = expert_routes(seeds, args)
    bimodal = {e["seed"] for e in expert_episodes if e.get("free_choice")}
    blocks: dict[str, dict[str, Any]] = {"expert": _expert_record(expert_episodes, bimodal)}
    paths: dict[str, Mapping[int, np.ndarray]] = {"expert": expert_paths}
    for name, path in policies.items():
        record, paths[name] = policy_routes(path, seeds, args)
        blocks[name] = {**_outcome(record["per_episode"], bimodal), **record}

    figures: dict[str, Any] = {
        "machine": machine_info(),
        "quick": args.quick,
        "protocol": {
            "name": PROTOCOL,
            "first_seed": args.first_seed,
            "episodes": args.episodes,
            "max_episode_steps": args.max_steps,
            "deviations": [
                f"{k}={v} (protocol: {p})"
                for k, v, p in (
                    ("episodes", args.episodes, protocol.episodes),
                    ("first_seed", args.first_seed, protocol.seed),
                    ("max_episode_steps", args.max_steps, 300),
                )
                if v != p
            ],
        },
        "rule": {
            "module": "l1flow_rl.experts.pusht.routes",
            "sweep_threshold_deg": args.sweep_threshold_deg,
            "contact_px": args.contact_px,
            "routes": list(ROUTES),
        },
        "deterministic": args.deterministic,
        "bimodal_seeds": sorted(bimodal),
        "policies": blocks,
    }
    shown = sorted(bimodal)[: args.plot_seeds]
    if shown:
        approaches = {k: {e["seed"]: e for e in b["per_episode"] if "route" in e} for k, b in blocks.items()}
        figures["figure"] = str(_plot(paths, approaches, shown, Path(args.out).with_suffix(".png")))
    figures["seconds"] = round(time.perf_counter() - start, 1)
    out = save_results(args.out, figures)

    expert = blocks["expert"]
    print(
        f"\nPushT, {args.episodes} seeds from {args.first_seed}, {args.max_steps} steps: "
        f"{len(bimodal)} bimodal starts (expert's planned side {expert['planned_side_on_bimodal']}); "
        f"the route rule agrees with the planner on {expert['agreement_on_bimodal']} of them"
    )
    columns = ["policy", "score", "success", *(f"{r} (bimodal)" for r in ROUTES), "between (all)"]
    print(format_table([_row(k, b) for k, b in blocks.items()], columns))
    print(f"\nsaved {out} ({figures['seconds']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
