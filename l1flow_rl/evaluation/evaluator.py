"""One evaluator for every task: N seeded episodes across parallel envs, ManiSkill's metrics plus
the simulator's own, each with a 95 % confidence interval.

Metric definitions follow ManiSkill's baseline evaluation (``ignore_terminations=True``): every
episode runs to the time limit; ``success_once`` = success at any step, ``success_at_end`` =
success at the last step, ``return`` = the sum of rewards. An episode that a simulator error ends
counts as a failure and carries the error message.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
from torchrl.modules import MultiStepActorWrapper

from l1flow_rl.envs.per_env import num_parallel_envs, seeded_reset, sim_error_messages
from l1flow_rl.evaluation.metrics import MEAN, RATE, summarize_metrics
from l1flow_rl.evaluation.schedule import REDUCTIONS, Schedule
from l1flow_rl.evaluation.videos import add_frames, write_video
from l1flow_rl.flow.samplers import sampler_name

__all__ = ["BUILTIN_METRICS", "evaluate", "sampler_record"]

CHUNK_KEY = "action_chunk"

#: the metrics every evaluation reports: name in the summary -> (name in the episode record, kind)
BUILTIN_METRICS: dict[str, tuple[str, str]] = {
    "success_once": ("success_once", RATE),
    "success_at_end": ("success_at_end", RATE),
    "return": ("return", MEAN),
    "episode_length": ("length", MEAN),
}


class _TimedActor(TensorDictModuleBase):
    """Times each call of the chunk actor (one call = one chunk for every env that needs one) and
    moves data between the env's and the policy's devices; MultiStepActorWrapper has no hook for
    either."""

    def __init__(self, actor: TensorDictModuleBase, device: torch.device) -> None:
        super().__init__()
        self.actor, self.device = actor, device
        self.in_keys, self.out_keys = list(actor.in_keys), list(actor.out_keys)
        self.latencies_s: list[float] = []

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        inputs = tensordict.select(*self.in_keys).to(self.device)
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        start = time.perf_counter()
        out = self.actor(inputs)
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self.latencies_s.append(time.perf_counter() - start)
        return tensordict.update(out.select(*self.out_keys).to(tensordict.device))


class _NetworkCalls:
    """Counts the chunk network's forward calls (a forward hook), so the summary states the NFE
    that actually ran, not only the one the sampler declares."""

    def __init__(self, actor: TensorDictModuleBase) -> None:
        self.count = 0
        net = getattr(getattr(actor, "policy", None), "net", None)
        self.handle = net.register_forward_hook(self._hook) if isinstance(net, torch.nn.Module) else None

    def _hook(self, *args: Any) -> None:
        self.count += 1

    def close(self) -> None:
        if self.handle is not None:
            self.handle.remove()


def sampler_record(actor: TensorDictModuleBase) -> dict[str, Any] | None:
    """What eval.json says about the sampler: its name, settings, declared NFE and prediction type."""
    sampler = getattr(getattr(actor, "policy", None), "sampler", None)
    if sampler is None:
        return None
    return {
        "name": sampler_name(sampler),
        "kwargs": sampler.settings(),
        "nfe": sampler.nfe,
        "prediction": sampler.prediction,
    }


def _policy_device(policy: torch.nn.Module) -> torch.device:
    tensor = next(iter(policy.parameters()), None)
    if tensor is None:
        tensor = next(iter(policy.buffers()), None)
    return tensor.device if tensor is not None else torch.device("cpu")


def _chunk_length(actor: TensorDictModuleBase, tensordict: TensorDictBase) -> int:
    steps = getattr(getattr(actor, "policy", None), "action_steps", None)
    if steps is not None:
        return int(steps)
    if CHUNK_KEY not in actor.out_keys:
        raise ValueError(f"the policy must write {CHUNK_KEY!r} [*B, K, A]; its out_keys are {actor.out_keys}")
    probe = actor(tensordict.select(*actor.in_keys).clone())[CHUNK_KEY]  # a policy without action_steps
    return int(probe.shape[tensordict.ndim])


def _check_metrics(metrics: Mapping[str, tuple[str, NestedKey]]) -> None:
    for name, spec in metrics.items():
        if name in BUILTIN_METRICS or name in ("length", "seed", "episode", "error", "video"):
            raise ValueError(f"episode metric {name!r} clashes with a built-in entry of the episode record")
        if not (isinstance(spec, tuple) and len(spec) == 2 and spec[0] in REDUCTIONS):
            raise ValueError(
                f"episode metric {name!r} must be (reduction, step entry) with reduction in {REDUCTIONS}, "
                f"got {spec!r}"
            )


def _summary(
    results: list[dict[str, Any]],
    latencies_s: list[float],
    network_calls: int,
    seed: int,
    wall_s: float,
    metrics: Mapping[str, tuple[str, NestedKey]],
) -> dict[str, Any]:
    results = sorted(results, key=lambda r: r["episode"])
    ms = np.asarray(latencies_s) * 1e3
    kinds = {record: kind for record, kind in BUILTIN_METRICS.values()}
    kinds.update({name: RATE if how == "any" else MEAN for name, (how, _) in metrics.items()})
    stats = summarize_metrics(results, kinds)
    # the summary names episode length "episode_length"; the episode record calls it "length"
    stats = {summary: stats[record] for summary, (record, _) in BUILTIN_METRICS.items()} | {
        name: stats[name] for name in metrics
    }
    return {
        "episodes": len(results),
        **{name: s["mean"] for name, s in stats.items()},
        "ci95": {name: [s["ci95_low"], s["ci95_high"]] for name, s in stats.items()},
        "ci_method": {name: s["interval"] for name, s in stats.items()},
        "latency_ms_median": float(np.median(ms)) if ms.size else math.nan,
        "latency_ms_p90": float(np.percentile(ms, 90)) if ms.size else math.nan,
        "policy_calls": int(ms.size),
        "network_calls": network_calls,
        "nfe_per_chunk": network_calls / ms.size if ms.size and network_calls else None,
        "errors": sum(r["error"] is not None for r in results),
        "seed": seed,
        "seeds": [r["seed"] for r in results],
        "wall_s": wall_s,
        "per_episode": results,
    }


def evaluate(
    policy: TensorDictModuleBase,
    env: EnvBase | Callable[[], EnvBase],
    episodes: int,
    seed: int = 0,
    *,
    deterministic: bool = False,
    episode_metrics: Mapping[str, tuple[str, NestedKey]] | None = None,
    video_dir: str | Path | None = None,
    video_episodes: int = 0,
    video_fps: int = 20,
    noise_seed: int | None = None,
) -> dict[str, Any]:
    """Run ``episodes`` episodes (episode ``i`` from seed ``seed + i``) across the env's parallel envs.

    Args:
        policy: a chunk actor writing ``"action_chunk"`` [*B, K, A] (e.g. :class:`~l1flow_rl.L1FlowActor`);
            it is run under TorchRL's ``MultiStepActorWrapper`` (re-plan every K steps and at every
            reset), unless it already is one.
        env: an env from :func:`l1flow_rl.envs.make_env` (batch size [N], with ``"is_init"``), or
            a function that makes one; with a function, an env that raises is rebuilt, and the
            env is closed at the end.
        episodes: how many episodes to run.
        seed: the first episode's seed.
        deterministic: sample chunks from zero noise (``ExplorationType.DETERMINISTIC``).
        episode_metrics: the simulator's own per-episode metrics, ``name -> (reduction, step entry)``
            (``SimulatorSpec.episode_metrics``, e.g. PushT's ``{"score": ("max", "reward")}``);
            reductions ``max``, ``sum``, ``last``, ``any``.
        video_dir: write videos (mp4) there.
        video_episodes: how many episodes, from the first, get a video.
        noise_seed: seeds the policy's noise instead of ``seed`` (the episodes keep their seeds): how
            much of a success figure is the sampler's noise draw.

    Returns:
        The means over episodes of ``success_once``, ``success_at_end``, ``return``,
        ``episode_length`` and each episode metric; ``ci95`` (name -> [low, high], Wilson for
        rates, Student t for means) and ``ci_method``; ``latency_ms_median``/``latency_ms_p90``
        (per policy call, i.e. per chunk); ``policy_calls``, ``network_calls`` and
        ``nfe_per_chunk`` (counted network evaluations); ``episodes``, ``errors``, ``seeds``, and
        ``per_episode`` (seed, metrics, error per episode). Policy noise is seeded from ``seed``
        (or ``noise_seed``); the caller's RNG is untouched.

    Example:
        >>> from l1flow_rl import L1FlowActor, evaluate
        >>> from l1flow_rl.envs import make_env
        >>> env = make_env("maniskill_pushcube", max_episode_steps=16)
        >>> actor = L1FlowActor.for_state(obs_dim=35, action_dim=4, down_dims=(32, 64))
        >>> evaluate(actor, env, episodes=2, seed=0)["episodes"]
        2
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    metrics = dict(episode_metrics or {})
    _check_metrics(metrics)
    make = env if not isinstance(env, EnvBase) else None
    env = make() if make is not None else env
    num_envs = num_parallel_envs(env)
    video_dir = Path(video_dir) if video_dir is not None else None
    schedule = Schedule(episodes, seed, num_envs, video_episodes if video_dir is not None else 0, metrics)
    wrapper = policy if isinstance(policy, MultiStepActorWrapper) else None
    inner = wrapper.actor if wrapper is not None else policy
    timed = _TimedActor(inner, _policy_device(inner))
    calls = _NetworkCalls(inner)
    # rollouts are inference: eval mode (image encoders centre-crop instead of random crops)
    was_training = inner.training
    inner.eval()
    exploration = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    devices = [timed.device] if timed.device.type == "cuda" else []
    start = time.perf_counter()

    def finish(slot: int, error: str | None) -> None:
        ep = schedule.slots[slot]
        if ep is not None and ep.frames and video_dir is not None:
            path = video_dir / f"episode{ep.index:03d}_seed{ep.seed}.mp4"
            ep.record["video"] = str(write_video(path, ep.frames, video_fps))
        schedule.finish(slot, error)

    def start_all() -> TensorDictBase:
        td = seeded_reset(env, None, [schedule.assign(i) for i in range(num_envs)])
        add_frames(schedule.slots, env)
        return td

    try:
        with torch.random.fork_rng(devices=devices), torch.no_grad(), set_exploration_type(exploration):
            torch.manual_seed(seed if noise_seed is None else noise_seed)
            td = start_all()
            if wrapper is None:
                executor = MultiStepActorWrapper(timed, n_steps=_chunk_length(inner, td), init_key="is_init")
            else:
                executor, wrapper.actor = wrapper, timed
            while schedule.running:
                td = executor(td)
                try:
                    td = env.step(td)
                except Exception as err:  # not the simulator's own error path: fail what ran, start afresh
                    message = f"{type(err).__name__}: {err}"
                    for i in range(num_envs):
                        finish(i, message)
                    env = _recover(env, make, err)
                    td = start_all()
                    continue
                next_td = td.get("next")
                reward, success, done, sim_error = _outcome(next_td, num_envs)
                extra = _step_metrics(next_td, metrics, num_envs)
                messages = sim_error_messages(env) if any(sim_error) else [None] * num_envs
                for i, ep in enumerate(schedule.slots):
                    if ep is not None and not sim_error[i]:  # a step that raised did not happen
                        ep.add_step(reward[i], success[i], {k: v[i] for k, v in extra.items()}, metrics)
                add_frames(schedule.slots, env)
                td = step_mdp(td)
                seeds: list[int | None] = [None] * num_envs
                for i in range(num_envs):
                    if done[i]:
                        finish(i, (messages[i] or "simulator error") if sim_error[i] else None)
                        seeds[i] = schedule.assign(i)
                if any(s is not None for s in seeds) and schedule.running:
                    td = seeded_reset(env, td, seeds)
                    add_frames(schedule.slots, env, [i for i, s in enumerate(seeds) if s is not None])
    finally:
        calls.close()
        inner.train(was_training)
        if wrapper is not None:
            wrapper.actor = inner
        if make is not None:  # not ``env.is_closed``: TorchRL's envs report True before they are closed
            env.close(raise_if_closed=False)
    wall = time.perf_counter() - start
    return _summary(schedule.results, timed.latencies_s, calls.count, seed, wall, metrics)


def _outcome(next_td: TensorDictBase, num_envs: int) -> tuple[list, list, list, list]:
    """Per env: reward, success, done, and whether the simulator failed (adapters that catch it)."""
    success = next_td.get("success", None)
    if success is None:
        raise KeyError(
            f"evaluate needs the env to write 'success' at every step; it wrote {list(next_td.keys())}"
        )
    sim_error = next_td.get("sim_error", torch.zeros(num_envs, dtype=torch.bool))
    return (
        next_td.get("reward").reshape(num_envs).tolist(),
        [bool(v) for v in success.reshape(num_envs).tolist()],
        [bool(v) for v in next_td.get("done").reshape(num_envs).tolist()],
        [bool(v) for v in sim_error.reshape(num_envs).tolist()],
    )


def _step_metrics(
    next_td: TensorDictBase, metrics: Mapping[str, tuple[str, NestedKey]], num_envs: int
) -> dict[str, list[float]]:
    """Per metric, the step entry's value of every env (one number per env)."""
    out = {}
    for name, (_, key) in metrics.items():
        value = next_td.get(key, None)
        if value is None:
            raise KeyError(
                f"episode metric {name!r} reads step entry {key!r}, which the env does not write; "
                f"it wrote {sorted(map(str, next_td.keys(include_nested=True)))}"
            )
        if value.numel() != num_envs:
            raise ValueError(
                f"episode metric {name!r}: entry {key!r} must hold one value per env, "
                f"got shape {tuple(value.shape)}"
            )
        out[name] = value.reshape(num_envs).float().tolist()
    return out


def _recover(env: EnvBase, make: Callable[[], EnvBase] | None, err: Exception) -> EnvBase:
    """After an exception escaped ``env.step``: a new env from ``make``, else the same one if it resets."""
    if make is not None:
        with contextlib.suppress(Exception):  # a broken env may not even close; the new one is what matters
            env.close()
        return make()
    try:
        env.reset()
    except Exception as reset_err:
        raise RuntimeError(
            f"the env raised ({type(err).__name__}: {err}) and cannot be reset; pass a function that makes "
            "the env to evaluate() so that it can be rebuilt"
        ) from reset_err
    return env
