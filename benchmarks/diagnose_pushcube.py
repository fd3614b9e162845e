"""Why a PushCube policy fails: where the cube, the goal and the hand are in failed episodes.

Plays a run's chosen checkpoint on the test seeds its ``eval.json`` lists as failures (and, for
comparison, on as many successes), each to a longer limit than the task's, and records per
episode: the step of first success (or none within the longer limit), the cube's distance to the
goal's centre at the task's limit and at its minimum (success: under the 0.1 m goal radius), how far
the cube moved, and how close the hand came to the cube. Policy noise differs from the run's
evaluation (seeded per episode here), so a listed failure may succeed: the rates are what count.

    .venv/bin/python -m benchmarks.diagnose_pushcube RUN_DIR [--limit 300] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import machine_info, save_results
from benchmarks.rollout_states import rollout_states

#: PushCube's flattened state: agent qpos (9), qvel (9), tcp_pose (7), goal_pos (3), obj_pose (7)
TCP, GOAL, CUBE = slice(18, 21), slice(25, 28), slice(28, 31)
GOAL_RADIUS = 0.1


def play(actor, task, seed: int, limit: int) -> dict:
    obs, first_success = rollout_states(actor, task, seed, noise_seed=seed, limit=limit)
    goal_dist = np.linalg.norm(obs[:, CUBE][:, :2] - obs[:, GOAL][:, :2], axis=1)
    hand_dist = np.linalg.norm(obs[:, TCP] - obs[:, CUBE], axis=1)
    at_limit = min(task.max_episode_steps, len(obs) - 1)
    return {
        "seed": seed,
        "first_success_step": first_success,
        "success_within_task_limit": first_success is not None and first_success <= task.max_episode_steps,
        "goal_dist_start": round(float(goal_dist[0]), 3),
        "goal_dist_at_task_limit": round(float(goal_dist[at_limit]), 3),
        "goal_dist_min": round(float(goal_dist.min()), 3),
        "goal_dist_min_step": int(goal_dist.argmin()),
        "cube_moved": round(float(np.linalg.norm(obs[-1, CUBE] - obs[0, CUBE])), 3),
        "hand_to_cube_min": round(float(hand_dist.min()), 3),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--limit", type=int, default=300, help="steps each episode may run")
    parser.add_argument(
        "--successes", type=int, default=None, help="successes replayed (default: as failures)"
    )
    parser.add_argument("--out", default="benchmarks/results/main_job_failures.json")
    args = parser.parse_args(argv)
    from l1flow_rl.config import load_task_config
    from l1flow_rl.workspace.checkpoint import load_actor

    torch.set_num_threads(1)
    result = json.loads((args.run_dir / "eval.json").read_text())
    episodes = result["per_episode"]
    failed = [e["seed"] for e in episodes if not e["success_once"]]
    succeeded = [e["seed"] for e in episodes if e["success_once"]][: args.successes or max(len(failed), 5)]
    actor, cfg = load_actor(args.run_dir / "checkpoints" / "best.pt", use_ema=True)
    task = load_task_config(cfg.task.name)
    rows = {
        "failed": [play(actor, task, s, args.limit) for s in failed],
        "succeeded": [play(actor, task, s, args.limit) for s in succeeded],
    }
    figures = {
        "run_dir": str(args.run_dir),
        "machine": machine_info(),
        "task_max_episode_steps": task.max_episode_steps,
        "replay_limit": args.limit,
        "eval_success_once": result["success_once"],
        "eval_episodes": len(episodes),
        "succeeded_first_success_steps": sorted(r["first_success_step"] for r in rows["succeeded"]),
        **rows,
        "failed_replays_succeeding_within_task_limit": sum(
            r["success_within_task_limit"] for r in rows["failed"]
        ),
        "failed_replays_succeeding_within_replay_limit": sum(
            r["first_success_step"] is not None for r in rows["failed"]
        ),
    }
    out = save_results(args.out, figures)
    for kind, items in rows.items():
        for r in items:
            print(kind, r)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
