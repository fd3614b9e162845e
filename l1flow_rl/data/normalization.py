"""Normalisation statistics from stored demonstrations, handed to a policy's normalisers once."""

from __future__ import annotations

from tensordict import TensorDictBase
from torch import nn
from torchrl.data import ReplayBuffer

from l1flow_rl.modules.policy import STATE_KEY, ChunkPolicy

__all__ = ["fit_normalizers"]


def _steps(data: TensorDictBase | ReplayBuffer) -> TensorDictBase:
    if isinstance(data, ReplayBuffer):
        return data.storage.get(slice(None))  # every stored step, not a sampled subset
    if isinstance(data, TensorDictBase):
        return data
    raise TypeError(
        f"expected episodes (a TensorDict of steps) or a replay buffer, got {type(data).__name__}"
    )


def fit_normalizers(
    policy: ChunkPolicy | nn.Module,
    data: TensorDictBase | ReplayBuffer,
    mode: str = "limits",
    *,
    obs_mode: str | None = None,
    observation_key: str = "observation",
    action_key: str = "action",
) -> ChunkPolicy:
    """Fit ``policy``'s observation and action normalisers on every stored step.

    Args:
        policy: a :class:`~l1flow_rl.modules.policy.ChunkPolicy`, or an actor holding one (``L1FlowActor``).
        data: episodes from :func:`~l1flow_rl.data.load_episodes`, or a buffer from
            :func:`~l1flow_rl.data.make_chunk_buffer` (its storage is read whole, padding excluded).
        mode: ``"limits"`` (to [-1, 1]) or ``"gaussian"`` (zero mean, unit variance).
        obs_mode: a different mode for the observations (default: ``mode``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from l1flow_rl import L1FlowActor
        >>> actor = L1FlowActor.for_state(obs_dim=3, action_dim=2, down_dims=(16, 32))
        >>> steps = TensorDict(
        ...     {"observation": torch.rand(50, 3) * 4, "action": torch.rand(50, 2) - 5}, batch_size=[50]
        ... )
        >>> policy = fit_normalizers(actor, steps)
        >>> bool(policy.action_normalizer.normalize(steps["action"]).abs().max() <= 1 + 1e-6)
        True
    """
    chunk_policy = getattr(policy, "policy", policy)
    if not isinstance(chunk_policy, ChunkPolicy):
        raise TypeError(f"expected a ChunkPolicy or an actor holding one, got {type(policy).__name__}")
    steps = _steps(data)
    for key in (observation_key, action_key):
        if key not in steps.keys():  # noqa: SIM118 (TensorDict has no __contains__)
            raise KeyError(
                f"cannot fit normalisers: the data lack {key!r} (has {sorted(map(str, steps.keys()))})"
            )
    observation = steps.get(observation_key)
    if isinstance(observation, TensorDictBase):
        # only flat entries have normalisers (images go through the encoder as they are)
        observation = {k: observation.get(k) for k in chunk_policy.obs_normalizer}
    elif set(chunk_policy.obs_normalizer.keys()) - {STATE_KEY}:
        raise KeyError(
            f"the data's {observation_key!r} is one tensor, but the policy normalises entries "
            f"{sorted(chunk_policy.obs_normalizer.keys())}"
        )
    return chunk_policy.fit_normalizers(observation, steps.get(action_key), mode=mode, obs_mode=obs_mode)
