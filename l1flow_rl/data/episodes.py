"""The one episode layout every importer produces, and the checks that guard it.

A loaded dataset is a flat TensorDict of steps, episodes one after another:

============================== ==================================================================
``"episode"``                  int64 [N], the episode id (constant over one episode, unique per episode)
``"step"``                     int64 [N], the index of the step inside its episode (0, 1, ...)
``"observation"``              float32 [N, D], or a TensorDict with ``"state"`` float32 [N, D] and
                               image entries uint8 [N, 3, H, W]; observation[t] is what the policy
                               saw before taking action[t]
``"action"``                   float32 [N, A]
``("next", "observation")``    the observation after action[t]: observation[t + 1] inside an episode,
                               and at its last step the final observation (kept when the format
                               records it; else the last observation repeated, and the metadata's
                               ``has_final_observation`` is False)
``("next", "reward")``         float32 [N, 1], the reward for action[t] (a format without rewards
                               stores 0 and says so in the metadata's ``has_rewards``)
``("next", "done")``           bool [N, 1], True on each episode's last step
``("next", "terminated")``     bool [N, 1], True on the last step of an episode that ended in a
                               terminal state (success or failure)
``("next", "truncated")``      bool [N, 1], True on the last step of an episode that stopped otherwise
``"episodes_metadata"``        non-tensor: format, source, env id, control (see
                               :mod:`l1flow_rl.data.metadata`)
============================== ==================================================================

Formats add what they know on top, e.g. ManiSkill's ``("next", "success")`` and
``("next", "sparse_reward")``.

Storing ``("next", "observation")`` whole costs a second copy of the observations. For state data
that is small; for image data it doubles the stored frames, which stay memory-mapped on disk
(``load_episodes(memmap_dir=...)``), and a batch reads only the To frames it needs. The flat copy is
kept because it is exactly what a TorchRL collector writes, so demonstrations and online data share
one layout and one storage.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from l1flow_rl.errors import UserInputError

__all__ = [
    "EpisodeDataError",
    "assemble_episode",
    "check_finite",
    "check_steps",
    "episode_bounds",
    "to_uint8_image",
]


class EpisodeDataError(UserInputError, ValueError):
    """Demonstration data that cannot be used; the message names the file, episode and key."""


def where(source: object, episode: object | None = None, key: str | None = None) -> str:
    parts = [str(source)]
    if episode is not None:
        parts.append(f"episode {episode}")
    if key is not None:
        parts.append(f"key {key!r}")
    return ": ".join(parts)


def as_tensor(value, source: object, episode: object, key: str) -> Tensor:
    try:
        return torch.as_tensor(np.asarray(value))
    except (OSError, RuntimeError, TypeError, ValueError) as err:  # h5py raises OSError on truncated data
        raise EpisodeDataError(f"{where(source, episode, key)}: cannot be read ({err})") from err


def check_finite(x: Tensor, source: object, episode: object, key: str) -> Tensor:
    """Raise unless every value of a floating-point array is finite; name the first bad step."""
    if x.is_floating_point():
        bad = ~torch.isfinite(x)
        if bad.any():
            step = int(bad.reshape(bad.shape[0], -1).any(1).nonzero()[0]) if x.dim() else 0
            raise EpisodeDataError(
                f"{where(source, episode, key)}: contains NaN or Inf (first at step {step})"
            )
    return x


def check_steps(
    x: Tensor, steps: int, source: object, episode: object, key: str, *, extra: int = 0
) -> Tensor:
    """``x`` must have ``steps`` (or ``steps + extra``) entries along dim 0; return its first ``steps``."""
    if x.dim() == 0 or x.shape[0] not in {steps, steps + extra}:
        expected = f"{steps}" if not extra else f"{steps} or {steps + extra}"
        got = tuple(x.shape)
        raise EpisodeDataError(
            f"{where(source, episode, key)}: has shape {got}, expected {expected} steps to match the actions"
        )
    return x[:steps]


def to_uint8_image(
    x: Tensor, source: object, episode: object, key: str, *, channels_last: bool, float_max: float = 255.0
) -> Tensor:
    """Images as uint8 [T, 3, H, W]. Float images are scaled by ``255 / float_max`` (Diffusion Policy
    stores whole values in [0, 255], LeRobot values in [0, 1]) and must then hold whole values in
    [0, 255]; anything else is refused rather than clipped."""
    if x.dim() != 4:
        raise EpisodeDataError(
            f"{where(source, episode, key)}: expected images [T, H, W, C], got {tuple(x.shape)}"
        )
    if channels_last:
        x = x.movedim(-1, 1)
    if x.shape[1] != 3:
        raise EpisodeDataError(
            f"{where(source, episode, key)}: expected 3 colour channels, got shape {tuple(x.shape)}"
        )
    if x.dtype == torch.uint8:
        return x.contiguous()
    if not x.is_floating_point():
        raise EpisodeDataError(f"{where(source, episode, key)}: images must be uint8 or float, got {x.dtype}")
    check_finite(x, source, episode, key)
    scaled = x.double() * (255.0 / float_max)
    rounded = scaled.round()
    if scaled.min() < 0 or scaled.max() > 255 or (scaled - rounded).abs().max() > 0.02:
        raise EpisodeDataError(
            f"{where(source, episode, key)}: float images must hold values in [0, {float_max:g}] on a 1/255 "
            f"grid; got values in [{float(x.min())}, {float(x.max())}]"
        )
    return rounded.to(torch.uint8).contiguous()


def assemble_episode(
    episode: int,
    observation: Tensor | Mapping[str, Tensor],
    action: Tensor,
    *,
    reward: Tensor | None = None,
    terminated: bool = False,
    final_observation: Tensor | Mapping[str, Tensor] | None = None,
    next_extra: Mapping[str, Tensor] | None = None,
) -> TensorDict:
    """One validated episode ([T] steps, arrays already checked) in the layout above.

    ``final_observation`` is the observation after the last action (one step, no time dimension);
    without it the last observation is repeated there (the reader's metadata must then say
    ``has_final_observation=False``).
    """
    steps = action.shape[0]
    obs = _observation(observation, steps)
    final = obs[-1] if final_observation is None else _observation(final_observation, None)
    next_obs = torch.cat([obs[1:], final.unsqueeze(0)], 0)
    done = torch.zeros(steps, 1, dtype=torch.bool)
    done[-1] = True
    term = done & terminated
    nxt = {
        "observation": next_obs,
        "reward": (reward.float() if reward is not None else torch.zeros(steps)).reshape(steps, 1),
        "done": done,
        "terminated": term,
        "truncated": done & ~term,
    }
    for key, value in (next_extra or {}).items():
        nxt[key] = value.reshape(steps, 1) if value.dim() == 1 else value
    return TensorDict(
        {
            "episode": torch.full((steps,), int(episode), dtype=torch.int64),
            "step": torch.arange(steps, dtype=torch.int64),
            "observation": obs,
            "action": action.float(),
            "next": TensorDict(nxt, batch_size=[steps]),
        },
        batch_size=[steps],
    )


def _observation(observation: Tensor | Mapping[str, Tensor], steps: int | None) -> Tensor | TensorDict:
    """Observations as stored: float flat entries, uint8 images kept; ``steps=None`` for one step."""
    if isinstance(observation, Mapping):
        return TensorDict(
            {k: v if v.dtype == torch.uint8 else v.float() for k, v in observation.items()},
            batch_size=[] if steps is None else [steps],
        )
    return observation.float()


def episode_bounds(episode: Tensor, source: object = "episodes") -> tuple[Tensor, Tensor]:
    """(start, end) row of each row's episode (end exclusive), from the ``"episode"`` column.

    Episodes must be stored as contiguous runs with distinct ids; anything else is refused because a
    window would silently straddle two episodes.
    """
    episode = episode.reshape(-1)
    n = episode.shape[0]
    if n == 0:
        raise EpisodeDataError(f"{where(source, key='episode')}: no steps")
    change = torch.ones(n, dtype=torch.bool)
    change[1:] = episode[1:] != episode[:-1]
    run_starts = change.nonzero().squeeze(1)
    run_ids = episode[run_starts]
    uniq, counts = torch.unique(run_ids, return_counts=True)
    if (counts > 1).any():
        raise EpisodeDataError(
            f"{where(source, int(uniq[counts > 1][0]), 'episode')}: the episode's steps are not contiguous "
            "(the id appears in more than one run of rows); store each episode's steps together"
        )
    run_ends = torch.cat([run_starts[1:], torch.tensor([n])])
    run_of_row = torch.cumsum(change.long(), 0) - 1
    return run_starts[run_of_row], run_ends[run_of_row]


def episode_lengths(data: TensorDictBase) -> dict[int, int]:
    ids, counts = torch.unique_consecutive(data.get("episode").reshape(-1), return_counts=True)
    return dict(zip(ids.tolist(), counts.tolist()))
