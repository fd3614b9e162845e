"""Noisy demonstrations for the flow-Q benchmark: a trained policy's rollouts with Gaussian action noise,
recorded by ManiSkill's own ``RecordEpisode`` (the ``.h5`` + ``.json`` pair every ManiSkill reader takes).

The flow-Q issue asks for a setting where imitation plateaus below the ceiling because of the data,
e.g. demonstrations with injected action noise. Each executed action is the policy's (a checkpoint
trained on clean expert demonstrations) plus N(0, ``--noise``^2) per dimension, clipped to the action
space; the recorded action is the one executed, with its reward (the task's ``reward_mode``), and an
episode ends at success (ManiSkill's termination) or at the time limit. Failed episodes are kept: the
data carry their rewards, which is what an offline critic learns from.

    .venv/bin/python -m benchmarks.make_noisy_demos --checkpoint runs/bc/checkpoints/best.pt \\
        --episodes 100 --noise 0.5 --out data/noisy/PushCube-v1.noise0.5.n100.h5

Seeds: episode i resets with ``--seed + i`` (the default 200000 keeps clear of the demonstration,
validation and test seeds). Prints the data's success rate and mean episode length.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from collections import deque
from pathlib import Path

import torch
from tensordict import TensorDict


def record(
    checkpoint: Path,
    episodes: int,
    noise: float,
    out: Path,
    seed: int = 200_000,
    max_episode_steps: int | None = None,
) -> dict:
    """Roll out ``checkpoint``'s policy with action noise ``noise`` for ``episodes`` episodes into
    ``out`` (``.h5``; its ``.json`` beside it). Returns the data's summary."""
    from l1flow_rl.envs.maniskill.env import make_gym_env
    from mani_skill.utils.wrappers import RecordEpisode
    from omegaconf import OmegaConf

    from l1flow_rl.config import TaskConfig
    from l1flow_rl.workspace.checkpoint import load_actor

    if out.suffix != ".h5":
        raise ValueError(f"--out {out}: expected a .h5 path (its .json is written beside it)")
    if noise < 0:
        raise ValueError(f"--noise {noise}: expected >= 0")
    actor, cfg = load_actor(checkpoint)
    task_cfg = OmegaConf.merge(OmegaConf.structured(TaskConfig), cfg.task)
    if max_episode_steps is not None:
        task_cfg.max_episode_steps = max_episode_steps
    task: TaskConfig = OmegaConf.to_object(task_cfg)  # type: ignore[assignment]
    if task.simulator != "maniskill" or task.obs_mode != "state":
        raise ValueError(f"{checkpoint}: trained on {task.name!r}; this script records ManiSkill state tasks")
    policy = actor.policy
    to, k = policy.obs_horizon, policy.action_steps
    # The actor is driven by hand on the raw gym env: RecordEpisode must wrap the env ManiSkill makes,
    # which the TorchRL adapter builds inside itself.
    tmp = Path(tempfile.mkdtemp(prefix=".noisy_", dir=out.parent if out.parent.exists() else None))
    env = make_gym_env(task, num_envs=1, device=torch.device("cpu"), render=False)
    env = RecordEpisode(
        env,
        output_dir=str(tmp),
        trajectory_name=out.stem,
        save_video=False,
        save_trajectory=True,
        record_reward=True,
        record_env_state=False,
    )
    low = torch.as_tensor(env.action_space.low, dtype=torch.float32).reshape(-1)
    high = torch.as_tensor(env.action_space.high, dtype=torch.float32).reshape(-1)
    gen = torch.Generator().manual_seed(seed)  # the injected action noise
    torch.manual_seed(seed)  # the policy's own sampling noise: the same file again for the same seed
    successes, lengths = 0, []
    try:
        try:
            for i in range(episodes):
                obs, _ = env.reset(seed=seed + i)
                history = deque([obs.reshape(1, -1).float()] * to, maxlen=to)
                plan: list[torch.Tensor] = []
                steps, success = 0, False
                while True:
                    if not plan:
                        td = TensorDict({"observation": torch.stack(list(history), 1)}, batch_size=[1])
                        with torch.no_grad():
                            chunk = actor(td)["action_chunk"][0]
                        plan = list(chunk[:k])
                    action = plan.pop(0) + noise * torch.randn(low.shape, generator=gen)
                    action = torch.minimum(torch.maximum(action, low), high)
                    obs, _, terminated, truncated, info = env.step(action.reshape(1, -1))
                    history.append(obs.reshape(1, -1).float())
                    steps += 1
                    if bool(terminated) or bool(truncated):
                        success = bool(info["success"])
                        break
                successes += success
                lengths.append(steps)
        finally:
            env.close()  # RecordEpisode writes the files on close
        out.parent.mkdir(parents=True, exist_ok=True)
        for suffix in (".h5", ".json"):  # complete files only under the final name
            shutil.move(str(tmp / f"{out.stem}{suffix}"), str(out.with_suffix(suffix)))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    summary = {
        "checkpoint": str(checkpoint),
        "task": task.name,
        "episodes": episodes,
        "noise": noise,
        "seed": seed,
        "success_rate": successes / episodes,
        "mean_length": sum(lengths) / episodes,
        "steps": sum(lengths),
    }
    out.with_suffix(".summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--noise", type=float, default=0.5, help="std of the Gaussian added to each action")
    parser.add_argument("--seed", type=int, default=200_000)
    parser.add_argument("--max-episode-steps", type=int, default=None)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    summary = record(args.checkpoint, args.episodes, args.noise, args.out, args.seed, args.max_episode_steps)
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
