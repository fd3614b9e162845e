"""One seeded episode of a chunk actor, with the state after every step: what the failure
diagnoses (``diagnose_pushcube``, ``diagnose_pickcube``, ``diagnose_can``) read positions from."""

from __future__ import annotations

import numpy as np
import torch


def rollout_states(
    actor, task, seed: int, *, noise_seed: int, limit: int | None = None, obs_horizon: int | None = None
) -> tuple[np.ndarray, int | None]:
    """(states [steps + 1, D] from the reset on, first success step or None) of one episode from
    ``seed``'s start, the policy's noise seeded with ``noise_seed``; ``limit`` overrides the task's
    episode limit."""
    from l1flow_rl.envs import make_env
    from l1flow_rl.envs.per_env import seeded_reset
    from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
    from torchrl.modules import MultiStepActorWrapper

    steps = limit or task.max_episode_steps
    options = {} if obs_horizon is None else {"obs_horizon": obs_horizon, "render": False}
    # a fresh env per episode: one env reused across seeded resets gave order-dependent episodes
    # (PickCube's third test start: 0.027 m apart from 0.025 m) and saved only ~10% of the time
    env = make_env(task, 1, max_episode_steps=steps, **options)
    frames, first_success = [], None
    try:
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            torch.manual_seed(noise_seed)
            td = seeded_reset(env, None, [seed])
            executor = MultiStepActorWrapper(actor, n_steps=actor.action_steps, init_key="is_init")
            frames.append(td["observation"][0, -1].numpy())
            for step in range(steps):
                td = env.step(executor(td))
                frames.append(td["next", "observation"][0, -1].numpy())
                if first_success is None and bool(td["next", "success"].reshape(-1)[0]):
                    first_success = step + 1
                if bool(td["next", "done"].reshape(-1)[0]):
                    break
                td = step_mdp(td)
    finally:
        env.close()
    return np.stack(frames), first_success
