"""One PushT demonstration: a seeded start, the planner's pushes, everything Diffusion Policy's zarr
layout records. Runs in a demo worker process (or in-process for tests)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from l1flow_rl.envs.pusht.geometry import block_keypoints, reset_state_for
from l1flow_rl.experts.pusht.planner import PushTPlanner

__all__ = ["Demo", "run_episode", "start_state"]

_REPRODUCIBLE_TRIES = 5


@dataclass
class Demo:
    """One episode's rows (``data/<key>`` arrays) and facts about it."""

    seed: int
    arrays: dict[str, np.ndarray]
    success: bool
    score: float  # Diffusion Policy's: the episode's best clip(coverage / 0.95, 0, 1)
    max_coverage: float
    side: str  # "left" / "right": the side the planner went around the block by choice; "none"
    steps: int
    seconds: float
    #: the first move's path to its contact: "left"/"right" around the block, "none" straight
    first_side: str = "none"
    #: whether that first side was a free choice (both ways viable, the episode's side decided)
    first_chosen: bool = False


def _make_env(images: bool, image_size: int, max_steps: int):
    os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
    # optional dependency: the simulator's gymnasium API
    import gym_pusht  # noqa: F401
    import gymnasium as gym

    return gym.make(
        "gym_pusht/PushT-v0",
        obs_type="pixels_agent_pos" if images else "state",
        observation_width=image_size,
        observation_height=image_size,
        max_episode_steps=max_steps,
        disable_env_checker=True,
    )


def _state(env) -> np.ndarray:
    u = env.unwrapped
    return np.array([*u.agent.position, *u.block.position, u.block.angle % (2 * np.pi)])


def start_state(env, seed: int):
    """Reset to ``seed``'s start in a form a stored float32 state reproduces exactly.

    gym-pusht steps the physics once inside ``reset``, which pushes a block the agent overlaps; the
    start is re-set from its own float32-rounded state until that is a fixed point, so that
    ``reset(options={"reset_to_state": reset_state_for(data/state[0])})`` gives the same start.
    Returns the observation and the float32 state, or None when no fixed point is reached."""
    env.reset(seed=seed)
    state = _state(env).astype(np.float32)
    for _ in range(_REPRODUCIBLE_TRIES):
        obs, _ = env.reset(options={"reset_to_state": reset_state_for(state.astype(np.float64))})
        now = _state(env).astype(np.float32)
        if np.array_equal(now, state):
            return obs, state
        state = now
    return None


def run_episode(
    seed: int, *, images: bool = False, image_size: int = 96, max_steps: int = 300
) -> Demo | None:
    """Run the planner from ``seed``'s start (None when the start cannot be made reproducible).

    Actions are rounded to float32 before they are executed, so that replaying the stored actions
    from the stored first state reproduces the episode bit for bit."""
    start = time.perf_counter()
    env = _make_env(images, image_size, max_steps)
    try:
        first = start_state(env, seed)
        if first is None:
            return None
        obs, state = first
        planner = PushTPlanner(np.random.default_rng([seed, 7]))
        rows: dict[str, list] = {"state": [], "action": [], "reward": [], "n_contacts": []}
        if images:
            rows["img"] = []
        side, coverage, done = "none", 0.0, False
        first: tuple[str, bool] | None = None
        while not done and len(rows["action"]) < max_steps:
            move = planner.plan(_state(env), np.array(env.unwrapped.agent.velocity))
            if move is None:
                break
            if first is None:
                first = (move.side or "none", move.chosen)
            if move.chosen and side == "none":
                side = move.side
            for target in move.actions:
                action = np.clip(np.asarray(target, dtype=np.float32), 0, 512)
                rows["state"].append(_state(env).astype(np.float32))
                if images:
                    rows["img"].append(obs["pixels"])
                obs, reward, terminated, truncated, info = env.step(action.astype(np.float64))
                rows["action"].append(action)
                rows["reward"].append(np.float32(reward))
                rows["n_contacts"].append(np.float32(info["n_contacts"]))
                coverage = max(coverage, float(info["coverage"]))
                if terminated or truncated:
                    done = True
                    break
        if not rows["action"]:
            return None
        arrays = {
            "action": np.stack(rows["action"]),
            "state": np.stack(rows["state"]),
            "keypoint": block_keypoints(np.stack(rows["state"]).astype(np.float64)).astype(np.float32),
            "n_contacts": np.stack(rows["n_contacts"])[:, None],
            "reward": np.stack(rows["reward"]),
        }
        if images:
            arrays["img"] = np.stack(rows["img"]).astype(np.uint8)
        arrays["state"][0] = state  # identical by construction; kept explicit for readers of this code
        success = coverage > env.unwrapped.success_threshold
        score = float(np.max(arrays["reward"]))
        steps = len(arrays["action"])
        first_side, first_chosen = first if first is not None else ("none", False)
        seconds = time.perf_counter() - start
        return Demo(seed, arrays, success, score, coverage, side, steps, seconds, first_side, first_chosen)
    finally:
        env.close()
