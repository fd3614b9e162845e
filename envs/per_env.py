"""Per-env operations on whatever :func:`make_env` returns: one env, CPU workers (ManiSkillAsyncEnv
or a ParallelEnv), or one physx_cuda scene, each possibly under transforms. Hand-written: TorchRL
reaches worker methods through attribute dispatch but has no per-env seeded reset or per-env query
of its own."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.batched_envs import BatchedEnvBase

__all__ = ["num_parallel_envs", "render_frames", "seeded_reset", "sim_error_messages"]


def _innermost(env: EnvBase) -> EnvBase:
    while isinstance(env, TransformedEnv):
        env = env.base_env
    return env


def num_parallel_envs(env: EnvBase) -> int:
    """N, for an env of batch size [N]."""
    if len(env.batch_size) != 1:
        raise ValueError(f"expected an env with batch size [num_envs], got {tuple(env.batch_size)}")
    return int(env.batch_size[0])


def seeded_reset(
    env: EnvBase, tensordict: TensorDictBase | None, seeds: Sequence[int | None]
) -> TensorDictBase:
    """Reset env ``i`` from ``seeds[i]``; ``None`` leaves env ``i`` running (a partial reset).

    ``tensordict`` is the current root data (after ``step_mdp``); it is updated in place with the
    reset envs' data, as ``EnvBase.reset`` does, so that a chunk executor's cache survives.
    With ``tensordict=None`` every seed must be given.
    """
    n = num_parallel_envs(env)
    if len(seeds) != n:
        raise ValueError(f"got {len(seeds)} seeds for {n} parallel envs")
    mask = torch.tensor([s is not None for s in seeds], device=env.device)
    if tensordict is None and not bool(mask.all()):
        raise ValueError("a first reset (tensordict=None) needs a seed for every env")
    if not bool(mask.any()):
        return tensordict
    base = _innermost(env)
    if isinstance(base, BatchedEnvBase):  # workers are unbatched: one seed each
        kwargs = {"list_of_kwargs": [{"seed": s} if s is not None else {} for s in seeds]}
    else:
        kwargs = {"seed": [s for s in seeds if s is not None]}
    if tensordict is None:
        return env.reset(**kwargs)
    tensordict.set("_reset", mask.reshape(n, 1))
    return env.reset(tensordict, **kwargs)


def _per_worker(env: EnvBase, method: str) -> list:
    base = _innermost(env)
    values = getattr(base, method)()
    if isinstance(values, (list, tuple, Tensor)):  # one value per env (ParallelEnv dispatch gives a list)
        return list(values)
    return [values] * num_parallel_envs(env)  # one value for the whole scene


def sim_error_messages(env: EnvBase) -> list[str | None]:
    """Per env: the simulator error that ended its last episode (``"sim_error"`` was True), else None."""
    return _per_worker(env, "sim_error_message")


def render_frames(env: EnvBase) -> Tensor:
    """The render camera's frame of every env: uint8 [N, H, W, 3] on the CPU (needs ``render=True``)."""
    return torch.stack(_per_worker(env, "render_frames"))
