"""One evaluator for every task: N seeded episodes across parallel envs, ManiSkill's metrics.

Metric definitions follow ManiSkill's baseline evaluation (``ignore_terminations=True``): every
episode runs to the time limit; ``success_once`` = success at any step, ``success_at_end`` =
success at the last step, ``return`` = the sum of rewards. An episode that a simulator error ends
counts as a failure and carries the error message.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
from torchrl.modules import MultiStepActorWrapper

__all__ = ["evaluate", "run_eval"]

CHUNK_KEY = "action_chunk"


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


@dataclass
class _Episode:
    index: int
    seed: int
    ret: float = 0.0
    length: int = 0
    success_once: bool = False
    success_at_end: bool = False
    frames: list[np.ndarray] | None = None
    record: dict[str, Any] = field(default_factory=dict)

    def close(self, error: str | None) -> dict[str, Any]:
        failed = error is not None
        return {
            "episode": self.index,
            "seed": self.seed,
            "success_once": self.success_once and not failed,
            "success_at_end": self.success_at_end and not failed,
            "return": self.ret,
            "length": self.length,
            "error": error,
            **self.record,
        }


class _Schedule:
    """Hands out episodes (index, seed = seed + index) to env slots until ``episodes`` are done."""

    def __init__(self, episodes: int, seed: int, num_envs: int, video_episodes: int) -> None:
        self.episodes, self.seed, self.video_episodes = episodes, seed, video_episodes
        self.next_index = 0
        self.spare_seed = seed + episodes  # envs with nothing left to run reset from seeds past the range
        self.slots: list[_Episode | None] = [None] * num_envs
        self.results: list[dict[str, Any]] = []

    def assign(self, slot: int) -> int:
        if self.next_index < self.episodes:
            ep = _Episode(self.next_index, self.seed + self.next_index)
            if ep.index < self.video_episodes:
                ep.frames = []
            self.slots[slot] = ep
            self.next_index += 1
            return ep.seed
        self.slots[slot] = None
        self.spare_seed += 1
        return self.spare_seed

    def finish(self, slot: int, error: str | None, video_dir: Path | None, fps: int) -> None:
        ep = self.slots[slot]
        if ep is None:
            return
        if ep.frames and video_dir is not None:
            import imageio

            video_dir.mkdir(parents=True, exist_ok=True)
            path = video_dir / f"episode{ep.index:03d}_seed{ep.seed}.mp4"
            imageio.mimwrite(path, ep.frames, fps=fps)
            ep.record["video"] = str(path)
        self.results.append(ep.close(error))
        self.slots[slot] = None

    @property
    def running(self) -> bool:
        return any(ep is not None for ep in self.slots)


def _add_frames(schedule: _Schedule, env: EnvBase, slots: list[int] | None = None) -> None:
    """Append the current frame to the filmed episodes in ``slots`` (default: all)."""
    from l1flow_rl.envs.per_env import render_frames

    slots = range(len(schedule.slots)) if slots is None else slots
    filmed = [i for i in slots if schedule.slots[i] is not None and schedule.slots[i].frames is not None]
    if not filmed:
        return
    frames = render_frames(env).numpy()
    for i in filmed:
        schedule.slots[i].frames.append(frames[i])


def _summary(
    results: list[dict[str, Any]], latencies_s: list[float], seed: int, wall_s: float
) -> dict[str, Any]:
    results = sorted(results, key=lambda r: r["episode"])
    ms = np.asarray(latencies_s) * 1e3

    def mean(key: str) -> float:
        return float(np.mean([r[key] for r in results]))

    return {
        "episodes": len(results),
        "success_once": mean("success_once"),
        "success_at_end": mean("success_at_end"),
        "return": mean("return"),
        "episode_length": mean("length"),
        "latency_ms_median": float(np.median(ms)) if ms.size else math.nan,
        "latency_ms_p90": float(np.percentile(ms, 90)) if ms.size else math.nan,
        "policy_calls": int(ms.size),
        "errors": sum(r["error"] is not None for r in results),
        "seed": seed,
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
    video_dir: str | Path | None = None,
    video_episodes: int = 0,
    video_fps: int = 20,
) -> dict[str, Any]:
    """Run ``episodes`` episodes (episode ``i`` from seed ``seed + i``) across the env's parallel envs.

    Args:
        policy: a chunk actor writing ``"action_chunk"`` [*B, K, A] (e.g. :class:`~l1flow_rl.L1FlowActor`);
            it is run under TorchRL's ``MultiStepActorWrapper`` (re-plan every K steps and at every
            reset), unless it already is one.
        env: an env from :func:`l1flow_rl.envs.make_env` (batch size [N], with ``"is_init"``), or
            a function that makes one; with a function, an env that raises is rebuilt, and the
            env is closed at the end.
        episodes: how many episodes to run. seed: the first episode's seed.
        deterministic: sample chunks from zero noise (``ExplorationType.DETERMINISTIC``).
        video_dir, video_episodes: write the first ``video_episodes`` episodes as mp4 there.

    Returns:
        ``success_once``, ``success_at_end``, ``return`` and ``episode_length`` (means over
        episodes), ``latency_ms_median``/``latency_ms_p90`` (per policy call, i.e. per chunk),
        ``episodes``, ``errors``, and ``per_episode`` (seed, success_once, success_at_end, return,
        length, error per episode). Policy noise is seeded from ``seed``; the caller's RNG is untouched.

    Example:
        >>> from l1flow_rl import L1FlowActor, evaluate
        >>> from l1flow_rl.envs import make_env
        >>> env = make_env("maniskill_pushcube", max_episode_steps=16)
        >>> actor = L1FlowActor.for_state(obs_dim=35, action_dim=4, down_dims=(32, 64))
        >>> evaluate(actor, env, episodes=2, seed=0)["episodes"]
        2
    """
    from l1flow_rl.envs.per_env import num_parallel_envs, seeded_reset, sim_error_messages

    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    make = env if not isinstance(env, EnvBase) else None
    env = make() if make is not None else env
    num_envs = num_parallel_envs(env)
    video_dir = Path(video_dir) if video_dir is not None else None
    schedule = _Schedule(episodes, seed, num_envs, video_episodes if video_dir is not None else 0)
    wrapper = policy if isinstance(policy, MultiStepActorWrapper) else None
    inner = wrapper.actor if wrapper is not None else policy
    timed = _TimedActor(inner, _policy_device(inner))
    exploration = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    devices = [timed.device] if timed.device.type == "cuda" else []
    start = time.perf_counter()

    def start_all() -> TensorDictBase:
        td = seeded_reset(env, None, [schedule.assign(i) for i in range(num_envs)])
        _add_frames(schedule, env)
        return td

    try:
        with torch.random.fork_rng(devices=devices), torch.no_grad(), set_exploration_type(exploration):
            torch.manual_seed(seed)
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
                        schedule.finish(i, message, video_dir, video_fps)
                    env = _recover(env, make, err)
                    td = start_all()
                    continue
                reward, success, done, sim_error = _outcome(td.get("next"), num_envs)
                messages = sim_error_messages(env) if any(sim_error) else [None] * num_envs
                for i, ep in enumerate(schedule.slots):
                    if ep is not None and not sim_error[i]:  # a step that raised did not happen
                        ep.ret += float(reward[i])
                        ep.length += 1
                        ep.success_once |= success[i]
                        ep.success_at_end = success[i]
                _add_frames(schedule, env)
                td = step_mdp(td)
                seeds: list[int | None] = [None] * num_envs
                for i in range(num_envs):
                    if done[i]:
                        error = (messages[i] or "simulator error") if sim_error[i] else None
                        schedule.finish(i, error, video_dir, video_fps)
                        seeds[i] = schedule.assign(i)
                if any(s is not None for s in seeds) and schedule.running:
                    td = seeded_reset(env, td, seeds)
                    _add_frames(schedule, env, [i for i, s in enumerate(seeds) if s is not None])
    finally:
        if wrapper is not None:
            wrapper.actor = inner
        if make is not None and not env.is_closed:
            env.close()
    return _summary(schedule.results, timed.latencies_s, seed, time.perf_counter() - start)


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


def run_eval(cfg) -> int:
    """``l1flow-rl eval checkpoint=PATH eval.episodes=N run_dir=DIR``: writes DIR/eval.json."""
    from omegaconf import OmegaConf

    from l1flow_rl.config import TaskConfig
    from l1flow_rl.envs import make_env, resolve_device
    from l1flow_rl.workspace.checkpoint import load_actor
    from l1flow_rl.workspace.report import format_summary

    if not cfg.checkpoint:
        print("l1flow-rl eval: pass checkpoint=PATH (a .pt file, or a run's checkpoints/ folder)")
        return 2
    device = resolve_device(cfg.device)
    actor, train_cfg = load_actor(cfg.checkpoint, use_ema=True, map_location=device)
    # The checkpoint's task is the one the policy acts in; the command line's task config only
    # applies (e.g. a longer max_episode_steps) when it names the same task.
    same_task = cfg.task.name == train_cfg.task.name
    if not same_task:
        print(f"evaluating on the checkpoint's task {train_cfg.task.name!r}, not {cfg.task.name!r}")
    task_node = OmegaConf.merge(OmegaConf.structured(TaskConfig), cfg.task if same_task else train_cfg.task)
    task: TaskConfig = OmegaConf.to_object(task_node)  # type: ignore[assignment]
    if (task.obs_mode, task.control_mode) != (train_cfg.task.obs_mode, train_cfg.task.control_mode):
        raise ValueError(
            f"task.obs_mode/control_mode {task.obs_mode}/{task.control_mode} differ from the checkpoint's "
            f"{train_cfg.task.obs_mode}/{train_cfg.task.control_mode}"
        )
    ev, run_dir = cfg.eval, Path(cfg.run_dir)
    obs_horizon = int(train_cfg.policy.obs_horizon)

    def make():
        return make_env(task, num_envs=ev.num_envs, device=device, obs_horizon=obs_horizon)

    result = evaluate(
        actor,
        make,
        episodes=ev.episodes,
        seed=ev.seed,
        deterministic=ev.deterministic,
        video_dir=run_dir / "videos" if ev.video_episodes > 0 else None,
        video_episodes=ev.video_episodes,
    )
    result = {"checkpoint": str(cfg.checkpoint), "task": task.name, **result}
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "eval.json").write_text(json.dumps(result, indent=2))
    headline = ("success_once", "success_at_end", "return", "episode_length", "episodes", "errors")
    rows = {key: result[key] for key in headline}
    rows.update(
        {
            "latency_ms_median (per chunk)": result["latency_ms_median"],
            "latency_ms_p90": result["latency_ms_p90"],
        }
    )
    print(f"{task.name}, {cfg.checkpoint}\n{format_summary(rows)}\nwrote {run_dir / 'eval.json'}")
    return 0
