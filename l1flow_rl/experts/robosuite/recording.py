"""Recording one robosuite episode as a robomimic demo dict (the scripted expert's, a perturbed or a
shifted replay's): the MuJoCo state before each action, robomimic's low-dimensional observations,
actions, rewards, termination and the model XML."""

from __future__ import annotations

import numpy as np

from l1flow_rl.envs.robosuite import sim

__all__ = ["record_episode"]


def record_episode(env, raw: dict, seed: int, act, gave_up, max_steps: int, extra: int) -> dict:
    """Play ``act()`` from the scene of ``seed`` (``raw``: the observation ``env.reset()`` returned)
    for up to ``max_steps`` steps, stopping ``extra`` steps into a success that holds (so that the
    last stored state is a success state too) or when ``gave_up()``; the robomimic demo dict with
    ``attrs["success"]``.

    ``raw`` must be reset's own observation: another forced read here would advance robosuite's
    observable sampling clocks by one substep, so that every step's observation would be sampled a
    substep before the step ends and no longer equal the one regenerated from the stored state."""
    states, actions, rewards, observations = [], [], [], []
    success, streak = False, 0
    for _ in range(max_steps):
        action = act()
        if action is None:
            break
        states.append(env.sim.get_state().flatten())
        observations.append(sim.robomimic_obs(raw, []))
        raw, reward = sim.step(env, action)
        actions.append(action)
        rewards.append(reward)
        streak = streak + 1 if env._check_success() else 0
        if streak > extra:
            success = True
            break
        if gave_up():
            break
    observations.append(sim.robomimic_obs(raw, []))
    obs = {k: np.stack([o[k] for o in observations[:-1]]) for k in observations[0]}
    next_obs = {k: np.stack([o[k] for o in observations[1:]]) for k in observations[0]}
    dones = np.zeros(len(actions), dtype=np.int64)
    dones[-1] = int(success)  # a failed episode is cut short (truncated), not terminated
    return {
        "states": np.stack(states),
        "actions": np.stack(actions),
        "rewards": np.asarray(rewards),
        "dones": dones,
        "obs": obs,
        "next_obs": next_obs,
        "model_file": env.sim.model.get_xml(),
        "attrs": {"seed": seed, "success": success},
    }
