"""Scripted robosuite demonstrations as a robomimic file.

Episodes run without cameras (several times faster:
``benchmarks/results/robosuite_throughput_robosuite_lift.json`` against ``..._lift_image.json``),
recording robomimic's low-dimensional observations, the MuJoCo state before each action, the
actions, rewards and the model XML. An image task's file then gets its camera observations by
replaying the stored states (:func:`l1flow_rl.envs.robosuite.regenerate.regenerate_observations`).
Episode ``i`` of a file made with ``seed`` resets the scene from seed ``seed + attempt``; failed
attempts are skipped.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import os
import time
from pathlib import Path

import numpy as np
import torch

from l1flow_rl.config import TaskConfig
from l1flow_rl.envs.robosuite import sim
from l1flow_rl.envs.robosuite.pool import worker_pool
from l1flow_rl.experts.quality import (
    QUALITY_LABELS,
    GripperLayout,
    check_quality,
    label_of,
    mixed_kinds,
    perturb_actions,
)
from l1flow_rl.experts.registry import DemoGenerationError
from l1flow_rl.experts.robosuite.recording import record_episode
from l1flow_rl.experts.robosuite.scripted import CLOSED, EXPERT_TASKS, OPEN, make_expert
from l1flow_rl.experts.robosuite.shifted import add_shifted_replays, check_shifted_replays

__all__ = ["dataset_path", "ensure_robosuite_demos", "replay_actions", "run_episode"]


def dataset_path(
    task: TaskConfig,
    num: int,
    data_dir: str | os.PathLike,
    seed: int = 0,
    quality: str = "expert",
    shifted_replays: int = 0,
) -> Path:
    views = "state" if task.obs_mode == "state" else "+".join(task.cameras) + f"{task.image_size}"
    mix = "" if quality == "expert" else f".{quality}"
    shift = f".shift{shifted_replays}" if shifted_replays else ""
    return (
        Path(data_dir)
        / "robosuite"
        / task.env_id
        / f"{task.env_id}.{task.control}.{views}.seed{seed}.n{num}{mix}{shift}.hdf5"
    )


def run_episode(env, task: TaskConfig, seed: int, max_steps: int | None = None) -> dict | None:
    """One scripted episode from the scene of ``seed``; the robomimic demo dict, or None when the
    expert failed. The episode runs 1-3 steps past its first success (while success holds), so
    that its last stored state (the one before the last action) is a success state too."""
    sim.seed_episode(env, seed)
    raw = env.reset()
    rng = np.random.default_rng([seed, 7])
    expert = make_expert(task.env_id, env, rng)
    expert.reset()
    extra = int(rng.integers(1, 4))
    demo = record_episode(
        env, raw, seed, expert.act, lambda: expert.failed, max_steps or task.max_episode_steps, extra
    )
    return demo if demo["attrs"]["success"] else None


def replay_actions(env, task: TaskConfig, seed: int, actions: np.ndarray) -> dict:
    """``actions`` played open loop from the scene of ``seed`` (a perturbed expert episode), up to
    ``task.max_episode_steps``; the robomimic demo dict, successful or not (``attrs["success"]``)."""
    sim.seed_episode(env, seed)
    raw = env.reset()
    queue = iter(np.asarray(actions, dtype=np.float64))
    extra = int(np.random.default_rng([seed, 8]).integers(1, 4))
    return record_episode(
        env, raw, seed, lambda: next(queue, None), lambda: False, task.max_episode_steps, extra
    )


# -- workers -----------------------------------------------------------------------------------------

_WORKER: dict = {}


def _worker_init(task: TaskConfig) -> None:
    torch.set_num_threads(1)
    _WORKER["task"] = task
    _WORKER["env"] = sim.make_from_env_args(sim.env_args_for_task(task, cameras=[]), source=task.name)


def _worker_episode(seed: int) -> tuple[int, dict | None, float]:
    start = time.perf_counter()
    demo = run_episode(_WORKER["env"], _WORKER["task"], seed)
    return seed, demo, time.perf_counter() - start


def _worker_replay(index: int, seed: int, actions: np.ndarray) -> tuple[int, dict]:
    return index, replay_actions(_WORKER["env"], _WORKER["task"], seed, actions)


def perturb_demos(
    task: TaskConfig, demos: list[dict], seed: int, *, workers: int = 2, progress: bool = True
) -> list[tuple[dict, str]]:
    """``demos`` (expert episodes) as a mixed-quality set: each keeps or changes its actions as its
    kind says (:func:`l1flow_rl.experts.quality.mixed_kinds`), played again from its own scene;
    (demo, label) pairs in the same order."""
    from tqdm import tqdm  # the app extra: progress bars of the demonstration CLI

    grip = GripperLayout("absolute", open=OPEN, closed=CLOSED)
    kinds = mixed_kinds(len(demos), seed)
    out: list[tuple[dict, str] | None] = [
        (d, "expert") if k == "expert" else None for d, k in zip(demos, kinds)
    ]
    jobs = []
    for i, (demo, kind) in enumerate(zip(demos, kinds)):
        if kind != "expert":
            demo_seed = int(demo["attrs"]["seed"])
            jobs.append(
                (
                    i,
                    demo_seed,
                    perturb_actions(demo["actions"], kind, np.random.default_rng([demo_seed, 11]), grip),
                )
            )
    task = dataclasses.replace(task, obs_mode="state", cameras=[])
    with worker_pool(workers, _worker_init, (task,)) as pool:
        futures = [pool.submit(_worker_replay, *job) for job in jobs]
        for fut in tqdm(
            cf.as_completed(futures), total=len(futures), desc="perturbed demos", disable=not progress
        ):
            i, played = fut.result()
            label = label_of(kinds[i], bool(played["attrs"]["success"]))
            played["attrs"] = {**played["attrs"], "perturbation": kinds[i]}
            out[i] = (played, label)
    return [pair for pair in out if pair is not None]


def _longest_failure_run(results: dict[int, dict | None], first: int) -> int:
    longest = run = 0
    seed = first
    while seed in results:
        run = run + 1 if results[seed] is None else 0
        longest = max(longest, run)
        seed += 1
    return longest


def generate(
    task: TaskConfig,
    num: int,
    seed: int = 0,
    *,
    workers: int = 2,
    max_failures: int = 50,
    progress: bool = True,
) -> tuple[list[dict], dict]:
    """``num`` successful demos (in seed order) and statistics (attempts, successes, seconds)."""
    # optional dependency (app extra): the progress bar
    from tqdm import tqdm

    task = dataclasses.replace(task, obs_mode="state", cameras=[])
    results: dict[int, dict | None] = {}
    durations: list[float] = []
    next_seed = seed
    bar = tqdm(total=num, desc=f"{task.env_id} demos", unit="demo", disable=not progress)
    with worker_pool(workers, _worker_init, (task,)) as pool:
        pending: set[cf.Future] = set()
        while True:
            successes = sum(1 for d in results.values() if d is not None)
            # every seed below next_seed is tried, so the first num successes are a function of seed
            while len(pending) < 2 * workers and successes + len(pending) < num:
                pending.add(pool.submit(_worker_episode, next_seed))
                next_seed += 1
            if not pending:
                break
            finished, pending = cf.wait(pending, return_when=cf.FIRST_COMPLETED)
            for fut in finished:
                s, demo, seconds = fut.result()
                results[s] = demo
                durations.append(seconds)
                bar.update(demo is not None)
            run = _longest_failure_run(results, seed)
            if run > max_failures:
                for fut in pending:
                    fut.cancel()
                raise DemoGenerationError(
                    f"task {task.name!r}: the scripted expert failed {run} episodes in a row (seeds from "
                    f"{seed}; {sum(d is None for d in results.values())} failures in {len(results)} episodes)"
                )
    bar.close()
    chosen = sorted(k for k, d in results.items() if d is not None)[:num]
    tried = max(chosen) - seed + 1
    stats = {
        "attempts": tried,
        "successes": num,
        "success_rate": num / tried,
        "seconds_per_episode": float(np.mean(durations)),
        "steps_per_demo": float(np.mean([len(results[s]["actions"]) for s in chosen])),
    }
    return [results[s] for s in chosen], stats


def ensure_robosuite_demos(
    task: TaskConfig,
    num: int,
    data_dir: str | os.PathLike,
    *,
    seed: int = 0,
    workers: int | None = None,
    max_consecutive_failures: int = 50,
    quality: str = "expert",
    shifted_replays: int = 0,
    progress: bool = True,
) -> Path:
    """The robomimic file of ``num`` scripted demonstrations of ``task`` under ``data_dir`` (made
    when missing; an image task's observations are regenerated from the states with its cameras).

    ``quality="mixed"``: ``num`` episodes of mixed quality instead (see
    :mod:`l1flow_rl.experts.quality`), each demo's label in its ``quality`` attribute and in
    robomimic's filter keys ``mask/<label>`` (``mask/train`` holds them all).

    ``shifted_replays=k``: those episodes, then the successful ones of ``k`` shifted replays of them
    (:mod:`l1flow_rl.experts.robosuite.shifted`), labelled ``shifted``."""
    # optional dependency: the writer imports h5py
    from l1flow_rl.data.formats.robomimic_writer import RobomimicWriter

    if task.env_id not in EXPERT_TASKS:
        raise DemoGenerationError(
            f"task {task.name!r}: no scripted robosuite expert for {task.env_id!r} (experts: "
            f"{sorted(EXPERT_TASKS)}); point data.path at a robomimic file"
        )
    if task.control != "absolute":
        raise DemoGenerationError(
            f"task {task.name!r}: the scripted experts act with absolute OSC_POSE targets; "
            "set control: absolute"
        )
    check_quality(quality)
    if shifted_replays:
        check_shifted_replays(task, shifted_replays)  # before the base episodes are made
    target = dataset_path(task, num, data_dir, seed, quality, shifted_replays)
    if target.is_file():
        return target
    workers = workers or min(2, os.cpu_count() or 1)
    state_task = dataclasses.replace(task, obs_mode="state", cameras=[])
    low_dim = dataset_path(state_task, num, data_dir, seed, quality, shifted_replays)
    if shifted_replays and not low_dim.is_file():
        base = ensure_robosuite_demos(
            state_task,
            num,
            data_dir,
            seed=seed,
            workers=workers,
            max_consecutive_failures=max_consecutive_failures,
            quality=quality,
            progress=progress,
        )
        add_shifted_replays(
            state_task, base, low_dim, shifted_replays, seed=seed, workers=workers, progress=progress
        )
    if not low_dim.is_file():
        demos, stats = generate(
            state_task, num, seed, workers=workers, max_failures=max_consecutive_failures, progress=progress
        )
        labelled = [(d, "expert") for d in demos]
        if quality == "mixed":
            labelled = perturb_demos(state_task, demos, seed, workers=workers, progress=progress)
        with RobomimicWriter(low_dim, sim.env_args_for_task(state_task, cameras=[])) as writer:
            for demo, label in labelled:
                demo["attrs"] = {**demo["attrs"], "quality": label}
                writer.add(demo)
            writer.add_mask("train", [f"demo_{i}" for i in range(num)])
            if quality == "mixed":
                for label in QUALITY_LABELS:
                    writer.add_mask(label, [f"demo_{i}" for i, (_, lb) in enumerate(labelled) if lb == label])
        if progress:
            print(
                f"{task.env_id}: {num} demos, expert success {stats['success_rate']:.2f} over "
                f"{stats['attempts']} seeds, {stats['seconds_per_episode']:.2f} s/episode"
            )
    if low_dim == target:
        return target
    # optional dependency: the module imports h5py
    from l1flow_rl.envs.robosuite.regenerate import regenerate_observations

    return regenerate_observations(
        low_dim, target, cameras=task.cameras, image_size=task.image_size, workers=workers, progress=progress
    )
