"""Subprocess entry that makes a mixed-quality ManiSkill file from an expert one (``demos.quality=mixed``).

    python -m l1flow_rl.experts.maniskill._perturb_worker SRC.h5 DST.h5 --seed 0

Each episode of ``SRC`` (an expert file in the task's obs/control mode, with its ``.json``) gets a
kind (:func:`l1flow_rl.experts.quality.mixed_kinds`). Expert episodes are copied; the others' actions
are perturbed and played from the episode's first stored env state, recording observations
(T + 1 rows), rewards, success, terminated and truncated as ManiSkill's replay tool does. The
``.json`` beside ``DST`` lists every episode with its ``quality`` label and ``perturbation``.
A subprocess, like the planner workers, so that the caller never imports ManiSkill (Vulkan) itself.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import h5py
import numpy as np
import torch

from l1flow_rl.experts.quality import GripperLayout, label_of, mixed_kinds, perturb_actions

#: pd_ee_delta_pos / pd_ee_delta_pose: one action unit moves the hand 10 cm (ManiSkill's Panda bounds)
DELTA_METRES_PER_UNIT = 0.1
#: ManiSkill's Panda gripper: 1 open, -1 closed
GRIPPER = GripperLayout("delta", open=1.0, closed=-1.0, metres_per_unit=DELTA_METRES_PER_UNIT)


def _first_state(group: h5py.Group) -> dict:
    return {k: _first_state(v) if isinstance(v, h5py.Group) else v[0] for k, v in group.items()}


def _play(env, episode: dict, first_state: dict, actions: np.ndarray, max_steps: int) -> dict:
    obs, _ = env.reset(seed=int(episode["episode_seed"]))
    env.unwrapped.set_state_dict(
        {
            k: (torch.as_tensor(v)[None] if not isinstance(v, dict) else _batched(v))
            for k, v in first_state.items()
        }
    )
    obs = env.unwrapped.get_obs()
    rows, rewards, success, truncated = [obs[0].cpu().numpy()], [], [], []
    done_at = None
    for t, action in enumerate(actions[:max_steps]):
        obs, reward, _, _, info = env.step(torch.as_tensor(action, dtype=torch.float32))
        rows.append(obs[0].cpu().numpy())
        rewards.append(float(reward[0]))
        success.append(bool(info["success"][0]))
        truncated.append(t + 1 == min(len(actions), max_steps) and not success[-1])
        if success[-1] and done_at is None:
            done_at = t
        if done_at is not None and t >= done_at + 2:  # like the expert files: a few steps into success
            break
    steps = len(rewards)
    return {
        "obs": np.stack(rows),
        "actions": np.asarray(actions[:steps], dtype=np.float32),
        "rewards": np.asarray(rewards, dtype=np.float32),
        "success": np.asarray(success),
        "terminated": np.asarray(success),  # ManiSkill terminates on success
        "truncated": np.asarray(truncated),
    }


def _batched(state: dict) -> dict:
    return {k: _batched(v) if isinstance(v, dict) else torch.as_tensor(v)[None] for k, v in state.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("src", type=Path)
    parser.add_argument("dst", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-steps", type=int, required=True)
    args = parser.parse_args(argv)

    import gymnasium as gym  # the maniskill extra: imported in the worker process only
    import mani_skill.envs  # noqa: F401  (registers the tasks)

    meta = json.loads(args.src.with_suffix(".json").read_text())
    info = meta["env_info"]
    kwargs = {k: v for k, v in info["env_kwargs"].items() if k in ("obs_mode", "control_mode", "reward_mode")}
    if kwargs.get("obs_mode") != "state":
        print(f"mixed quality needs a state file; {args.src} holds {kwargs.get('obs_mode')}", file=sys.stderr)
        return 2
    env = gym.make(info["env_id"], sim_backend="physx_cpu", **kwargs)
    kinds = mixed_kinds(len(meta["episodes"]), args.seed)
    episodes = []
    tmp = args.dst.with_name(f".{args.dst.name}.partial")
    with h5py.File(args.src, "r") as src, h5py.File(tmp, "w") as dst:
        for episode, kind in zip(meta["episodes"], kinds):
            name = f"traj_{episode['episode_id']}"
            record = {**episode, "perturbation": kind}
            if kind == "expert":
                src.copy(src[name], dst, name)
                episodes.append({**record, "quality": "expert"})
                continue
            rng = np.random.default_rng([int(episode["episode_seed"]), 11])
            actions = perturb_actions(src[name]["actions"][()], kind, rng, GRIPPER)
            played = _play(env, episode, _first_state(src[name]["env_states"]), actions, args.max_steps)
            group = dst.create_group(name)
            for key, value in played.items():
                group.create_dataset(key, data=value)
            ok = bool(played["success"].any())
            episodes.append(
                {
                    **record,
                    "quality": label_of(kind, ok),
                    "success": ok,
                    "elapsed_steps": len(played["actions"]),
                }
            )
            print(f"episode {episode['episode_id']}: {kind} -> {episodes[-1]['quality']}", flush=True)
    env.close()
    json_tmp = args.dst.with_name(f".{args.dst.stem}.json.partial")
    json_tmp.write_text(json.dumps({**meta, "episodes": episodes, "quality": "mixed"}, indent=1))
    json_tmp.replace(args.dst.with_suffix(".json"))
    tmp.replace(args.dst)  # the h5 last: its presence means the pair is complete
    return 0


if __name__ == "__main__":
    sys.exit(main())
