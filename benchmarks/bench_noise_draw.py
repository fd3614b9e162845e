"""How much of a validation figure is the sampler's noise draw: one checkpoint re-scored on the same
episode seeds (the validation split) under several seeds of the policy's noise.

Why: the 20-demo Can start validated 0.22 on the CPU and 0.04 on an H200 (benchmarks/run_records/device14),
same checkpoint, same episode seeds; only the noise generator differed. A checkpoint chosen by its
validation figure is chosen partly on this draw.

    python -m benchmarks.bench_noise_draw --checkpoint runs/ft_bc_can_n20/checkpoints/best.pt \\
        --out benchmarks/results/noise_draw_robosuite_can.json
"""

from __future__ import annotations

import argparse
import math

from l1flow_rl.envs import make_env

from benchmarks.common import machine_info, save_results
from benchmarks.sweep import mean_and_spread
from l1flow_rl.evaluation import evaluate
from l1flow_rl.evaluation.plan import task_from
from l1flow_rl.workspace.checkpoint import load_actor


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=10_000, help="first episode seed (validation)")
    parser.add_argument(
        "--noise-seeds", type=int, nargs="+", default=None, help="default: the episode seed, +1, +2, +3"
    )
    parser.add_argument("--num-envs", type=int, default=2)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    noise_seeds = args.noise_seeds or [args.seed + i for i in range(4)]
    actor, cfg = load_actor(args.checkpoint, use_ema=True)
    task = task_from(cfg.task)
    rows = []
    # one env for every pass: evaluate reseeds each episode, so the passes differ only in the noise
    env = make_env(task, num_envs=args.num_envs, obs_horizon=int(cfg.policy.obs_horizon), render=False)
    try:
        for noise_seed in noise_seeds:
            result = evaluate(actor, env, episodes=args.episodes, seed=args.seed, noise_seed=noise_seed)
            rate, ci = result["success_once"], result["ci95"]["success_once"]
            rows.append({"noise_seed": noise_seed, "success_once": rate, "ci95": ci})
            print(f"noise seed {noise_seed}: success_once {rate:.2f}")
    finally:
        env.close()
    rates = [r["success_once"] for r in rows]
    spread = mean_and_spread(rates)
    mean = spread["mean"]
    data = {
        "checkpoint": args.checkpoint,
        "task": task.name,
        "episodes": args.episodes,
        "episode_seeds": {"first": args.seed, "episodes": args.episodes},
        "rows": rows,
        "mean": mean,
        "min": spread["min"],
        "max": spread["max"],
        # the spread one would see from episodes alone at this rate (binomial), beside the measured one
        "binomial_std_at_mean": math.sqrt(mean * (1 - mean) / args.episodes),
        "std_over_noise_seeds": spread["std"],
        "machine": machine_info(),
    }
    save_results(args.out, data)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
