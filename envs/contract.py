"""The env contract of :mod:`l1flow_rl.envs.registry`, as a check a simulator's tests can run.

Hand-written: TorchRL's ``check_env_specs`` checks that outputs match the specs, not this
project's keys, dtypes and per-env seeded resets.

    from l1flow_rl.envs.contract import check_env_contract
    check_env_contract(make_env("my_task", num_envs=2))
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from l1flow_rl.envs.per_env import num_parallel_envs, seeded_reset
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import check_env_specs, step_mdp

__all__ = ["ContractError", "check_env_contract"]

_FLAGS = ("done", "terminated", "truncated", "success")


class ContractError(AssertionError):
    """An env breaks the contract; the message names the entry and what was expected."""


def _observations(td: TensorDictBase) -> dict[str, torch.Tensor]:
    obs = td.get("observation")
    if isinstance(obs, torch.Tensor):
        return {"observation": obs.clone()}
    return {f"observation.{k}": v.clone() for k, v in obs.items(include_nested=True, leaves_only=True)}


def _check_outputs(td: TensorDictBase, n: int, where: str, reward: bool) -> None:
    for key in (*_FLAGS, *(("reward",) if reward else ())):
        if key not in td:
            raise ContractError(f"{where}: no {key!r} entry (has {sorted(map(str, td.keys()))})")
        value = td.get(key)
        dtype = torch.float32 if key == "reward" else torch.bool
        if tuple(value.shape) != (n, 1) or value.dtype != dtype:
            raise ContractError(
                f"{where}: {key!r} is {value.dtype} {tuple(value.shape)}, expected {dtype} ({n}, 1)"
            )
    for name, value in _observations(td).items():
        if value.shape[0] != n:
            raise ContractError(f"{where}: {name!r} has shape {tuple(value.shape)}, expected ({n}, ...)")
        if value.dtype not in (torch.float32, torch.uint8):
            raise ContractError(
                f"{where}: {name!r} is {value.dtype}, expected float32 (state) or uint8 (images)"
            )


def _same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor], rows: Sequence[int]) -> bool:
    return all(torch.equal(a[k][list(rows)], b[k][list(rows)]) for k in a)


def check_env_contract(env: EnvBase, seeds: Sequence[int] = (3, 4, 5, 6), steps: int = 2) -> None:
    """Raise :class:`ContractError` unless ``env`` (batch ``[N]``, as ``make_env`` returns it)
    honours the contract: TorchRL's spec check; the output entries with their dtypes and shapes;
    the same seed starts the same episode, in any env slot; a partial reset restarts only the envs
    it names (N > 1). Takes a few resets and a few times ``steps`` steps."""
    n = num_parallel_envs(env)
    if len(seeds) < n + 1:
        raise ValueError(f"need at least {n + 1} seeds for {n} envs, got {len(seeds)}")
    check_env_specs(env)
    first = seeded_reset(env, None, list(seeds[:n]))
    _check_outputs(first, n, "reset", reward=False)
    fresh = _observations(first)
    td = first
    for _ in range(steps):
        td = env.rand_step(td)
        _check_outputs(td.get("next"), n, "step", reward=True)
        td = step_mdp(td)
    again = _observations(seeded_reset(env, None, list(seeds[:n])))
    if not _same(fresh, again, range(n)):
        raise ContractError(f"reset(seed={list(seeds[:n])}) twice gave different observations")
    if n < 2:
        return
    shifted = _observations(seeded_reset(env, None, list(seeds[1 : n + 1])))  # env i: seed i + 1
    if not all(torch.equal(shifted[k][0], fresh[k][1]) for k in fresh):
        raise ContractError(f"seed {seeds[1]} started different episodes in env 0 and env 1")
    # A partial reset of env 0 leaves the others running: their next step is the one they would
    # have taken without it (TorchRL keeps their rows of the reset output either way, so only a
    # step shows whether the simulator restarted them). Zero actions keep both runs identical.
    zero = env.full_action_spec.zero()

    def run(partial_reset: bool) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor] | None]:
        td = seeded_reset(env, None, list(seeds[1 : n + 1]))
        for _ in range(steps):
            td = step_mdp(env.step(td.update(zero)))
        restarted = None
        if partial_reset:
            td = seeded_reset(env, td, [seeds[0], *([None] * (n - 1))])
            restarted = _observations(td)
        return _observations(env.step(td.update(zero)).get("next")), restarted

    expected, _ = run(partial_reset=False)
    got, restarted = run(partial_reset=True)
    if not _same(restarted, fresh, [0]):
        raise ContractError(f"a partial reset of env 0 with seed {seeds[0]} did not start its episode")
    if not _same(got, expected, range(1, n)):
        raise ContractError("a partial reset of env 0 restarted or changed the envs it did not name")
