"""PushT env throughput: the TorchRL adapter against raw gym-pusht measured in the same run.

Steps per second for raw ``gym.make("gym_pusht/PushT-v0")`` (the baseline), the adapter in process
(``PushTEnv``, 1 env), ``make_env`` with ``backend=serial`` (2 envs in process) and with worker
processes (``backend=parallel``, 2 envs), for the keypoints and pixels_agent_pos observations.
Prints and saves ``benchmarks/results/pusht_env.json``. ``--quick`` steps each setting a few times to
check the script end to end (its rates mean nothing) and saves ``pusht_env_quick.json`` unless
``--out`` says otherwise.

    python -m benchmarks.speed.bench_pusht_env --steps 600 [--quick] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.lib.common import RESULTS_DIR, machine_info, parse_args, save_results

DEFAULT_OUT = RESULTS_DIR / "pusht_env.json"
#: where --quick saves without --out: beside the real file, never over it
QUICK_OUT = DEFAULT_OUT.with_name("pusht_env_quick.json")
#: --quick: steps per setting (2 per env for the 2-env settings) and warm-up steps of the 2-env envs
QUICK_STEPS, QUICK_WARMUP = 4, 2
WARMUP = 20


def raw_rate(obs_type: str, steps: int) -> float:
    import gym_pusht  # noqa: F401
    import gymnasium as gym

    env = gym.make("gym_pusht/PushT-v0", obs_type=obs_type, disable_env_checker=True)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    start = time.perf_counter()
    for _ in range(steps):
        _, _, term, trunc, _ = env.step(rng.uniform(100, 400, 2))
        if term or trunc:
            env.reset()
    return steps / (time.perf_counter() - start)


def torchrl_rate(env, steps: int) -> float:
    from torchrl.envs.utils import step_mdp

    n = int(env.batch_size[0]) if env.batch_size else 1
    td = env.reset()
    gen = torch.Generator().manual_seed(0)
    start = time.perf_counter()
    for _ in range(steps // n):
        td["action"] = torch.rand(*env.batch_size, 2, generator=gen) * 300 + 100
        td = step_mdp(env.step(td))
        if td["done"].any():
            td = env.reset(td.set("_reset", td["done"].clone()))
    return (steps // n) * n / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--out", default=None, help=f"default: {DEFAULT_OUT} ({QUICK_OUT.name} with --quick)")
    parser.add_argument("--quick", action="store_true", help="tiny budget: checks the script, not speed")
    args = parse_args(parser, argv)
    warmup = WARMUP
    if args.quick:
        args.steps, warmup = QUICK_STEPS, QUICK_WARMUP
    out = Path(args.out or (QUICK_OUT if args.quick else DEFAULT_OUT))
    torch.set_num_threads(1)
    os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
    from l1flow_rl.envs import make_env
    from l1flow_rl.envs.pusht.env import PushTEnv

    from l1flow_rl.config import load_task_config

    result = {
        "quick": args.quick,
        "steps": args.steps,
        "loadavg_before": os.getloadavg(),
        "cpu_count": os.cpu_count(),
        "machine": machine_info(),
    }
    for task, obs_type in (("pusht", "state"), ("pusht_image", "pixels_agent_pos")):
        rows = {"raw_gym_pusht": raw_rate(obs_type, args.steps)}
        rows["adapter_1env"] = torchrl_rate(PushTEnv(load_task_config(task)), args.steps)
        for backend in ("serial", "parallel"):
            env = make_env(task, num_envs=2, backend=backend)
            torchrl_rate(env, warmup)  # workers started and warm
            rows[f"make_env_2envs_{backend}"] = torchrl_rate(env, args.steps)
            env.close()
        base = rows["raw_gym_pusht"]
        result[task] = {"steps_per_s": rows, "ratio_to_raw": {k: v / base for k, v in rows.items()}}
        print(task, json.dumps(result[task], indent=1), flush=True)
    result["loadavg_after"] = os.getloadavg()
    save_results(out, result)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
