"""``ensure_pusht_demos``: PushT demonstrations from the scripted planner, made in parallel worker
processes with a progress bar, cached under ``data_dir`` as Diffusion Policy zarr replay buffers."""

from __future__ import annotations

import math
import multiprocessing
import multiprocessing.pool
import os
import signal
import threading
from collections.abc import Iterator, Sequence
from functools import partial
from pathlib import Path

import numpy as np

from l1flow_rl.data.formats.dp_zarr_writer import write_dp_zarr
from l1flow_rl.envs.workers import standard_start_method
from l1flow_rl.experts.pusht.episode import Demo, run_episode
from l1flow_rl.experts.registry import DemoGenerationError

__all__ = ["SIDE_CODES", "demo_path", "ensure_pusht_demos", "run_episodes"]

#: meta/side: how each episode went around the block (see PushTPlanner)
SIDE_CODES = {"none": 0, "left": 1, "right": 2}
IMAGE_MODES = ("pixels", "pixels_agent_pos")


def _wants_images(task) -> bool:
    return task.obs_mode in IMAGE_MODES


def demo_path(task, num: int, data_dir: str | os.PathLike, seed: int) -> Path:
    """Where ``num`` demonstrations from ``seed`` on are cached (image demos carry ``data/img``)."""
    kind = f"img{int(task.image_size)}" if _wants_images(task) else "lowdim"
    limit = "" if int(task.max_episode_steps) == 300 else f"_T{int(task.max_episode_steps)}"
    return Path(data_dir) / "pusht" / f"pusht_{kind}_n{num}_seed{seed}{limit}.zarr"


def _worker(seed: int, images: bool, image_size: int, max_steps: int) -> tuple[int, Demo | None, str | None]:
    try:
        return seed, run_episode(seed, images=images, image_size=image_size, max_steps=max_steps), None
    except Exception as err:
        return seed, None, f"{type(err).__name__}: {err}"


def _ignore(signum, frame) -> None:
    """SIGTERM's stand-in in the parent while the pool spawns: ignored here, default in the workers."""


def _spawn_pool(workers: int) -> multiprocessing.pool.Pool:
    """A spawn pool whose workers ignore SIGINT and die on SIGTERM.

    Ctrl-C reaches the whole process group; only the parent should handle it (and terminate the
    pool), not each worker with a traceback. Workers start with the parent's ignored disposition
    (kept across exec, and Python leaves an ignored SIGINT alone), which also covers a worker still
    importing when Ctrl-C comes. ``pool.terminate()`` ends the workers with SIGTERM and then joins
    them without a timeout, so a worker must not inherit an ignored SIGTERM (a parent started with
    it ignored: seen, the Ctrl-C test hung for good in a full test run). A Python handler is not
    inherited across exec, so a no-op one keeps SIGTERM ignored here while the workers start with
    the default."""
    standard_start_method()  # inside a loky worker (hydra's joblib launcher) spawn would fail
    context = multiprocessing.get_context("spawn")
    if threading.current_thread() is not threading.main_thread():
        return context.Pool(workers)  # signal handlers belong to the main thread
    previous_int = signal.signal(signal.SIGINT, signal.SIG_IGN)
    term_ignored = signal.getsignal(signal.SIGTERM) == signal.SIG_IGN
    if term_ignored:
        signal.signal(signal.SIGTERM, _ignore)
    try:
        return context.Pool(workers)
    finally:
        signal.signal(signal.SIGINT, previous_int)
        if term_ignored:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)


def run_episodes(
    seeds: Sequence[int],
    *,
    images: bool = False,
    image_size: int = 96,
    max_steps: int = 300,
    workers: int | None = None,
    progress: bool = True,
    desc: str = "PushT demos",
) -> Iterator[tuple[int, Demo | None, str | None]]:
    """Run the planner on ``seeds`` in ``workers`` spawned processes (default: one per CPU core, at
    most the number of seeds), yielding ``(seed, demo or None, error or None)`` in seed order."""
    workers = max(1, min(workers or os.cpu_count() or 1, len(seeds)))
    job = partial(_worker, images=images, image_size=image_size, max_steps=max_steps)
    bar = pool = None
    try:
        if workers == 1:
            results = map(job, seeds)
        else:
            pool = _spawn_pool(workers)
            results = pool.imap(job, seeds)
        if progress:
            # optional dependency (app extra). Shown once the pool is up, since a Ctrl-C while the
            # pool starts (SIGINT ignored, see _spawn_pool) is lost
            from tqdm import tqdm

            bar = tqdm(total=len(seeds), desc=desc, unit="episode", dynamic_ncols=True)
        for item in results:
            if bar is not None:
                bar.update(1)
            yield item
        if pool is not None:
            pool.close()
            pool.join()
            pool = None
    finally:
        if bar is not None:
            bar.close()
        if pool is not None:
            pool.terminate()


def ensure_pusht_demos(
    task,
    num: int,
    data_dir: str | os.PathLike,
    *,
    seed: int = 0,
    workers: int | None = None,
    progress: bool = True,
    max_failure_rate: float = 0.5,
) -> Path:
    """``num`` successful planner demonstrations of PushT (env seeds ``seed``, ``seed + 1``, ...;
    unsuccessful seeds are skipped and recorded), as a Diffusion Policy zarr store under
    ``data_dir/pusht``: ``data/{action,state,keypoint,n_contacts}`` (+ ``data/img`` uint8 for image
    tasks), ``meta/episode_ends``, and extras Diffusion Policy's readers ignore: ``data/reward``,
    ``meta/{seed,side,score,terminated}``. Reused when it exists.

    Raises :class:`DemoGenerationError` when more than ``max_failure_rate`` of a round's seeds fail.
    """
    if num < 1:
        raise ValueError(f"demos.num must be >= 1, got {num}")
    path = demo_path(task, num, data_dir, seed)
    if path.exists():
        return path
    images = _wants_images(task)
    demos: list[Demo] = []
    skipped: dict[int, str] = {}
    next_seed = seed
    while len(demos) < num:
        want = num - len(demos)
        seeds = list(range(next_seed, next_seed + math.ceil(want * 1.1) + 1))
        next_seed = seeds[-1] + 1
        failed = 0
        for s, demo, error in run_episodes(
            seeds,
            images=images,
            image_size=int(task.image_size),
            max_steps=int(task.max_episode_steps),
            workers=workers,
            progress=progress,
            desc=f"PushT demos ({len(demos)}/{num} kept)",
        ):
            if demo is not None and demo.success:
                if len(demos) < num:
                    demos.append(demo)
                continue
            failed += 1
            skipped[s] = error or ("no reproducible start" if demo is None else f"score {demo.score:.3f}")
        if failed > max_failure_rate * len(seeds):
            raise DemoGenerationError(
                f"PushT planner failed on {failed} of {len(seeds)} seeds ({dict(list(skipped.items())[:5])})"
            )
    write_dp_zarr(
        path,
        [d.arrays for d in demos],
        meta={
            "seed": np.array([d.seed for d in demos], dtype=np.int64),
            "side": np.array([SIDE_CODES[d.side] for d in demos], dtype=np.int8),
            "score": np.array([d.score for d in demos], dtype=np.float32),
            "terminated": np.array([d.success for d in demos], dtype=bool),
        },
        attrs={
            "env_id": task.env_id,
            "control_mode": task.control_mode,
            "expert": "l1flow_rl.experts.pusht (push planner with lookahead in gym-pusht's physics)",
            "side_codes": SIDE_CODES,
            "skipped_seeds": {str(k): v for k, v in skipped.items()},
            "reset_to_state": "l1flow_rl.envs.pusht.geometry.reset_state_for(data/state[first row])",
        },
    )
    return path
