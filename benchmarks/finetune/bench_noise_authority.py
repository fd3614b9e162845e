"""How far a chunk policy's input noise can move the actions it executes: the steering authority that
DSRL (a noise-space actor choosing the sampler's initial noise w, ``|w| <= 1.5``) has over a frozen
policy.

For each checkpoint, ``--states`` observation histories [N, To, ...] are drawn from the demonstrations
it was trained on (its run's chunk buffer, seeded: the same windows for every checkpoint trained on the
same file with the same horizons), and the executed steps [To-1, To-1+K) of the chunk
``policy.sample_chunk(obs, noise=w)`` are compared, per action dimension:

* ``std_noise``: the std over ``--draws`` draws of w ~ N(0, I) clipped to +-1.5 (DSRL's bound), per
  state and step, then averaged over states and steps;
* ``std_states``: the std over states of the chunk at w = 0 (how much the actions vary where the
  policy goes);
* ``authority``: their ratio (the same in either unit: the normaliser is affine per dimension);
* ``mean_abs_shift``: mean |chunk(w) - chunk(0)| over the clipped draws;
* ``std_noise_corners``: the std for w = 1.5 sign(N(0, I)) (the bound's corners);
* ``std_noise_wide``: the std for w ~ N(0, 9) (beyond the bound).

Each in environment units (``env``) and in the policy's normalised action units (``normalized``,
``policy.action_normalizer.normalize``: [-1, 1] per dimension under the ``limits`` normaliser).
Samplers that draw fresh noise inside the loop (DDPM's ancestral steps) get the same per-step noise
for every w (one generator seed for every decode), so only the initial noise is steered, as DSRL
steers it; their ``std_step_noise`` is the std over per-step noise alone at w = 0.

    python -m benchmarks.finetune.bench_noise_authority \\
        --checkpoint pickcube_l1flow=runs/ft_bc_pickcube_n25/checkpoints/best.pt \\
        --out benchmarks/results/noise_authority.json
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from benchmarks.lib.common import machine_info, parse_args, save_results
from benchmarks.report.finetune import render_noise_authority
from l1flow_rl.modules.policy import ChunkPolicy

__all__ = ["BOUND", "WIDE_STD", "action_groups", "noise_authority", "parse_checkpoints"]

#: DSRL's noise bound (``NoisePolicy``'s default): the steering actor's w lies in [-1.5, 1.5]
BOUND = 1.5
#: the std of the draws beyond the bound (w ~ N(0, WIDE_STD^2))
WIDE_STD = 3.0
#: the per-dimension statistics :func:`noise_authority` returns for each unit
STATISTICS = ("std_noise", "std_states", "mean_abs_shift", "std_noise_corners", "std_noise_wide")


def action_groups(action_dim: int) -> dict[str, list[int]]:
    """Which action dimensions are the arm's position, its rotation and the gripper: the project's
    end-effector controls put position first and the gripper last (ManiSkill ``pd_ee_delta_pos``:
    x, y, z, gripper; robosuite OSC: x, y, z, axis-angle, gripper); fewer than 4 dims (PushT) are all
    position, with no gripper."""
    dims = list(range(action_dim))
    if action_dim < 4:
        return {"position": dims}
    groups = {"position": dims[:3], "rotation": dims[3:-1], "gripper": dims[-1:]}
    return {k: v for k, v in groups.items() if v}


def _executed(policy: ChunkPolicy, observation: Tensor, noise: Tensor, step_seed: int) -> Tensor:
    """Executed steps [N, K, A] (environment units) of the chunk from initial noise ``noise``; the
    sampler's own per-step noise, if it draws any, comes from a generator seeded ``step_seed``."""
    generator = torch.Generator(device=noise.device).manual_seed(step_seed)
    return policy.executable(policy.sample_chunk(observation, noise=noise, generator=generator))


def draws_per_step_noise(policy: ChunkPolicy, observation: Tensor, seed: int = 0) -> bool:
    """Whether the sampler draws noise beyond its initial chunk (two decodes of w = 0 with different
    per-step seeds differ)."""
    w = torch.zeros(*policy.batch_dims(observation), policy.pred_horizon, policy.action_dim)
    return not torch.equal(
        _executed(policy, observation, w, seed), _executed(policy, observation, w, seed + 1)
    )


@torch.no_grad()
def noise_authority(
    policy: ChunkPolicy,
    observation: Tensor,
    *,
    draws: int = 16,
    bound: float = BOUND,
    wide_std: float = WIDE_STD,
    seed: int = 0,
) -> dict[str, Any]:
    """The steering statistics of ``policy`` at observation histories ``observation`` [N, To, ...].

    Returns ``{"env": {stat: [A]}, "normalized": {stat: [A]}, "authority": [A], "per_step_noise": bool}``
    with ``stat`` each of :data:`STATISTICS` (``std_step_noise`` added where the sampler draws per-step
    noise). Needs ``draws >= 2`` and ``N >= 2`` (each std is over draws or over states).
    """
    n = policy.batch_dims(observation)
    if len(n) != 1 or n[0] < 2 or draws < 2:
        raise ValueError(f"need observation [N >= 2, To, ...] and draws >= 2, got batch {n}, draws {draws}")
    shape = (n[0], policy.pred_horizon, policy.action_dim)
    gen = torch.Generator().manual_seed(seed)
    step_seed = seed + 1  # every decode gets the same per-step noise: only w varies

    def stack(make: Callable[[], Tensor]) -> Tensor:  # [D, N, K, A]: one decode per draw of w
        return torch.stack([_executed(policy, observation, make(), step_seed) for _ in range(draws)])

    base = _executed(policy, observation, torch.zeros(shape), step_seed)  # [N, K, A]
    chunks = {
        "clipped": stack(lambda: torch.randn(shape, generator=gen).clamp(-bound, bound)),
        "corners": stack(lambda: bound * torch.sign(torch.randn(shape, generator=gen))),
        "wide": stack(lambda: wide_std * torch.randn(shape, generator=gen)),
    }
    per_step = draws_per_step_noise(policy, observation, seed)
    if per_step:  # w = 0, the per-step noise drawn afresh each time
        zero = torch.zeros(shape)
        chunks["steps"] = torch.stack(
            [_executed(policy, observation, zero, step_seed + 1 + k) for k in range(draws)]
        )

    def spread(x: Tensor) -> Tensor:  # [D, N, K, A] -> std over draws, mean over states and steps
        return x.std(0).mean((0, 1))

    out: dict[str, Any] = {"per_step_noise": per_step}
    for unit, f in (("env", lambda x: x), ("normalized", policy.action_normalizer.normalize)):
        b, c = f(base), {k: f(v) for k, v in chunks.items()}
        stats = {
            "std_noise": spread(c["clipped"]),
            "std_states": b.std(0).mean(0),
            "mean_abs_shift": (c["clipped"] - b).abs().mean((0, 1, 2)),
            "std_noise_corners": spread(c["corners"]),
            "std_noise_wide": spread(c["wide"]),
        }
        if per_step:
            stats["std_step_noise"] = spread(c["steps"])
        out[unit] = stats
    env = out["env"]
    out["authority"] = env["std_noise"] / env["std_states"].clamp_min(1e-12)
    return out


def parse_checkpoints(items: list[str]) -> dict[str, Path] | str:
    """``NAME=PATH`` items as {name: path}, or the one-line reason the first bad item is refused."""
    found: dict[str, Path] = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            return f"argument --checkpoint: {item!r} is not NAME=PATH"
        if name in found:
            return f"argument --checkpoint: the name {name!r} is given twice"
        if not Path(path).is_file():
            return f"argument --checkpoint: {item!r}: no file at {path}"
        found[name] = Path(path)
    return found


def _rounded(value: Any) -> Any:
    if isinstance(value, Tensor):
        return [round(float(v), 6) for v in value.reshape(-1)]
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    return value


def measure(path: Path, args: argparse.Namespace) -> dict[str, Any]:
    """One checkpoint's figures, with what it is: task, method, sampler, the windows it was read at."""
    from benchmarks.success.bench_open_loop import demonstration_windows
    from l1flow_rl.workspace.checkpoint import load_actor, load_checkpoint

    actor, cfg = load_actor(path)
    policy: ChunkPolicy = actor.policy
    windows = demonstration_windows(cfg, args.states, args.seed)
    stats = noise_authority(policy, windows["observation"], draws=args.draws, seed=args.seed)
    start = policy.obs_horizon - 1
    return {
        "checkpoint": str(path),
        "task": cfg.task.name,
        "env_id": cfg.task.get("env_id"),
        "control_mode": cfg.task.get("control_mode"),
        "method": cfg.policy.name,
        "loss": cfg.policy.loss,
        "sampler": {
            "name": cfg.policy.sampler,
            "kwargs": dict(cfg.policy.get("sampler_kwargs") or {}),
            "nfe": policy.sampler.nfe,
            "per_step_noise": stats.pop("per_step_noise"),
        },
        "finetuned": bool(cfg.policy.get("finetune")),
        "dataset": load_checkpoint(path).get("dataset"),
        "demos": cfg.demos.num,
        "obs_horizon": policy.obs_horizon,
        "pred_horizon": policy.pred_horizon,
        "executed_steps": [start, start + policy.action_steps],
        "action_dim": policy.action_dim,
        "action_normalizer": policy.action_normalizer.mode,
        "dim_groups": action_groups(policy.action_dim),
        **_rounded(stats),
    }


def _fail(parser: argparse.ArgumentParser, message: str) -> None:
    parser.exit(2, f"{parser.prog}: error: {message}\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", nargs="+", required=True, metavar="NAME=PATH")
    parser.add_argument("--states", type=int, default=256, help="demonstration windows per checkpoint")
    parser.add_argument("--draws", type=int, default=16, help="noise draws per state")
    parser.add_argument("--seed", type=int, default=0, help="seeds the windows and the noise")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the machine is shared)")
    parser.add_argument("--out", default="benchmarks/results/noise_authority.json")
    args = parse_args(parser, argv)
    checkpoints = parse_checkpoints(args.checkpoint)
    if isinstance(checkpoints, str):
        _fail(parser, checkpoints)
    for flag in ("states", "draws"):
        if getattr(args, flag) < 2:
            _fail(parser, f"argument --{flag}: must be >= 2 (a std needs two values)")
    torch.set_num_threads(args.threads)
    results = {}
    for name, path in checkpoints.items():
        results[name] = measure(path, args)
        print(f"{name}: authority {results[name]['authority']}", flush=True)
    figures = {
        "machine": machine_info("cpu"),
        "states": args.states,
        "draws": args.draws,
        "seed": args.seed,
        "bound": BOUND,
        "wide_std": WIDE_STD,
        "states_source": (
            "windows of each checkpoint's training demonstrations, drawn by its run's chunk buffer "
            "(benchmarks.success.bench_open_loop.demonstration_windows) with the seed"
        ),
        "noise": {
            "std_noise": f"w ~ N(0, I) clipped to +-{BOUND} (DSRL's bound)",
            "std_noise_corners": f"w = {BOUND} * sign(N(0, I)) (the bound's corners)",
            "std_noise_wide": f"w ~ N(0, {WIDE_STD**2:g} I) (beyond the bound)",
            "std_states": "the chunk at w = 0 across states",
            "authority": "std_noise / std_states per action dim",
            "per_step_noise": (
                "samplers that draw noise inside the loop (DDPM's ancestral steps) get the same "
                "per-step noise for every w: only the initial noise is steered, as DSRL steers it; "
                "std_step_noise is the spread from the per-step noise alone at w = 0"
            ),
        },
        "checkpoints": results,
    }
    save_results(args.out, figures)
    print(render_noise_authority(figures))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
