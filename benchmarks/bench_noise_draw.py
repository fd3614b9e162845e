"""How much of a validation figure is the sampler's noise draw: one checkpoint re-scored on the same
episode seeds (the validation split) under several seeds of the policy's noise.

Why: the 20-demo Can start validated 0.22 on the CPU and 0.04 on an H200 (benchmarks/run_records/device14),
same checkpoint, same episode seeds; only the noise generator differed. A checkpoint chosen by its
validation figure is chosen partly on this draw.

Per start, it also counts under how many draws each episode seed succeeds: a policy whose failures
are the start's (never solved, whatever the noise) gains little from imitating its own successes,
which sit on starts it already solves; one whose failures are the draw's (a start solved under some
draws only) has successes to learn from on the very starts it fails. The JSON sets the observed split
(always / sometimes / never) beside the split expected if success ignored the start.

``--action-noise SIGMA`` adds Gaussian noise of that scale to every executed action (kept inside the
env's action bounds): a probe of whether a perturbed collection reaches starts the policy never
solves under its own noise.

    python -m benchmarks.bench_noise_draw --checkpoint runs/ft_bc_can_n20/checkpoints/best.pt \\
        --out benchmarks/results/noise_draw_robosuite_can.json
"""

from __future__ import annotations

import argparse
import math

import torch
from l1flow_rl.envs import make_env
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from benchmarks.common import machine_info, save_results
from benchmarks.sweep import mean_and_spread
from l1flow_rl.evaluation import evaluate
from l1flow_rl.evaluation.plan import task_from
from l1flow_rl.workspace.checkpoint import load_actor


class ActionNoise(TensorDictModuleBase):
    """The actor's chunk plus N(0, sigma^2) per action, clamped to the env's bounds [low, high].

    Not TorchRL's ``AdditiveGaussianModule`` (the collector's): the evaluator runs the chunk actor and
    reads its ``policy.action_steps``, and that module needs a spec of the chunk's shape."""

    def __init__(
        self,
        actor: TensorDictModuleBase,
        sigma: float,
        low: torch.Tensor,
        high: torch.Tensor,
        per: str = "step",
    ):
        super().__init__()
        self.actor, self.sigma, self.per = actor, sigma, per
        self.policy = getattr(actor, "policy", None)  # the evaluator reads the executed steps from it
        self.in_keys, self.out_keys = actor.in_keys, actor.out_keys
        self.register_buffer("low", low)
        self.register_buffer("high", high)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict = self.actor(tensordict)
        key = self.out_keys[0]
        chunk = tensordict.get(key)
        # "chunk": one draw per chunk, the same offset on each of its steps (a drift of the
        # delta-position target rather than a jitter); "step": an independent draw per action
        shape = chunk.shape if self.per == "step" else (*chunk.shape[:-2], 1, chunk.shape[-1])
        noisy = chunk + self.sigma * torch.randn(shape, dtype=chunk.dtype, device=chunk.device)
        return tensordict.set(key, torch.maximum(torch.minimum(noisy, self.high), self.low))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=10_000, help="first episode seed (validation)")
    parser.add_argument(
        "--noise-seeds", type=int, nargs="+", default=None, help="default: the episode seed, +1, +2, +3"
    )
    parser.add_argument("--num-envs", type=int, default=2)
    parser.add_argument(
        "--action-noise", type=float, default=0.0, help="std of Gaussian noise on every executed action"
    )
    parser.add_argument(
        "--noise-per",
        choices=("step", "chunk"),
        default="step",
        help="an independent draw per executed action, or one per chunk held over its steps",
    )
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    if args.action_noise < 0:  # before the checkpoint and the simulator are loaded
        parser.error(f"--action-noise {args.action_noise}: expected a std >= 0")
    noise_seeds = args.noise_seeds or [args.seed + i for i in range(4)]
    actor, cfg = load_actor(args.checkpoint, use_ema=True)
    task = task_from(cfg.task)
    rows, wins = [], {}
    # one env for every pass: evaluate reseeds each episode, so the passes differ only in the noise
    env = make_env(task, num_envs=args.num_envs, obs_horizon=int(cfg.policy.obs_horizon), render=False)
    if args.action_noise > 0:
        space, dim = env.action_spec.space, env.action_spec.shape[-1]  # bounds per env: take one row
        low, high = space.low.reshape(-1, dim)[0], space.high.reshape(-1, dim)[0]
        actor = ActionNoise(actor, args.action_noise, low, high, per=args.noise_per)
    try:
        for noise_seed in noise_seeds:
            result = evaluate(actor, env, episodes=args.episodes, seed=args.seed, noise_seed=noise_seed)
            rate, ci = result["success_once"], result["ci95"]["success_once"]
            rows.append({"noise_seed": noise_seed, "success_once": rate, "ci95": ci})
            for episode in result["per_episode"]:
                wins[episode["seed"]] = wins.get(episode["seed"], 0) + int(bool(episode["success_once"]))
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
        "action_noise": args.action_noise,
        "noise_per": args.noise_per,
        "episode_seeds": {"first": args.seed, "episodes": args.episodes},
        "rows": rows,
        "mean": mean,
        "min": spread["min"],
        "max": spread["max"],
        # the spread one would see from episodes alone at this rate (binomial), beside the measured one
        "binomial_std_at_mean": math.sqrt(mean * (1 - mean) / args.episodes),
        "std_over_noise_seeds": spread["std"],
        "per_start": per_start_split(wins, len(noise_seeds), mean),
        "machine": machine_info(),
    }
    save_results(args.out, data)
    return 0


def per_start_split(wins: dict[int, int], draws: int, rate: float) -> dict:
    """How often each start (episode seed) succeeds over ``draws`` noise draws: the counts of starts
    solved under every draw, some draws and none, beside the counts expected if every start succeeded
    independently at the overall ``rate`` (the start then explains nothing)."""
    starts = len(wins)
    always = sum(w == draws for w in wins.values())
    never = sum(w == 0 for w in wins.values())
    expected_always, expected_never = starts * rate**draws, starts * (1 - rate) ** draws
    return {
        "draws": draws,
        "starts": starts,
        "always": always,
        "sometimes": starts - always - never,
        "never": never,
        "expected_if_start_ignored": {
            "always": expected_always,
            "sometimes": starts - expected_always - expected_never,
            "never": expected_never,
        },
        # successes per start, for a histogram; keys as strings (JSON)
        "wins_per_start": {str(seed): w for seed, w in sorted(wins.items())},
    }


if __name__ == "__main__":
    raise SystemExit(main())
