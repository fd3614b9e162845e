"""The command line shared by the failure diagnoses that put each episode in one phase
(``diagnose_pickcube``, ``diagnose_can``): several checkpoints played on the same episode seeds
under the same noise seeds, each episode's row from the task's ``play``, its phase from ``phase``."""

from __future__ import annotations

import argparse
from collections import Counter
from collections.abc import Callable

import torch

from benchmarks.common import machine_info, save_results


def diagnose(
    argv: list[str] | None,
    *,
    description: str,
    env_id: str,
    play: Callable[[object, object, int, int, int], dict],
    phase: Callable[[dict], str],
    constants: dict,
) -> int:
    """Parse ``--checkpoints NAME=PATH ...``, refuse a checkpoint of another task than ``env_id``
    (state observations), play ``--episodes`` seeds from ``--seed`` with each, and save the rows,
    the phase counts and ``constants`` (the thresholds the phases used) to ``--out``."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--checkpoints", nargs="+", required=True, help="NAME=PATH, one per policy")
    parser.add_argument("--seed", type=int, default=100_000, help="first episode seed (test split)")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--noise-seed", type=int, default=0, help="added to each episode's seed")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    named = []
    for item in args.checkpoints:  # before any checkpoint or simulator is loaded
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            parser.error(f"--checkpoints {item!r}: expected NAME=PATH")
        named.append((name, path))
    from l1flow_rl.evaluation.plan import task_from
    from l1flow_rl.workspace.checkpoint import load_actor

    torch.set_num_threads(1)
    seeds = range(args.seed, args.seed + args.episodes)
    policies = {}
    for name, path in named:
        actor, cfg = load_actor(path, use_ema=True)
        task = task_from(cfg.task)
        if task.env_id != env_id or task.obs_mode != "state":
            parser.error(f"--checkpoints {name}={path}: task {task.name} is not {env_id} (state)")
        rows = [play(actor, task, int(cfg.policy.obs_horizon), s, s + args.noise_seed) for s in seeds]
        for row in rows:
            row["phase"] = phase(row)
        counts = Counter(r["phase"] for r in rows)
        policies[name] = {"checkpoint": path, "phases": dict(counts.most_common()), "episodes": rows}
        print(name, dict(counts.most_common()))
    data = {
        "episode_seeds": {"first": args.seed, "episodes": args.episodes},
        "noise_seed_offset": args.noise_seed,
        **constants,
        "policies": policies,
        "machine": machine_info(),
    }
    print(f"wrote {save_results(args.out, data)}")
    return 0
