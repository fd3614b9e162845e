"""ManiSkill demonstrations made offline (``l1flow-rl demos``), cached and resumable.

Batches of seeds go to a worker process (:mod:`l1flow_rl.experts.maniskill._plan_worker`) that runs
ManiSkill's motion-planning solution (it records ``pd_joint_pos``) and replays the successes with
ManiSkill's replay tool into the task's observation and control mode, recording rewards. Under ``DATA_DIR``::

    maniskill/<env_id>[.<tag>]/planned/seeds_<a>-<b>.{h5,json,attempts.json}       planner output, any mode
    maniskill/<env_id>[.<tag>]/<obs>.<control>.<reward>/seeds_<a>-<b>.{h5,json}    replayed batches
    maniskill/<env_id>[.<tag>]/<obs>.<control>.<reward>/<env_id>.seed<s>.n<N>.{h5,json}   the dataset

``.<tag>``: where our own solution replaces ManiSkill's (:mod:`l1flow_rl.experts.maniskill.solutions`).

A batch appears under its final name only once complete (work happens in a temporary directory and
is renamed), so an interrupted run resumes from the last finished batch. Seeds run consecutively
from ``seed``; generation stops with :class:`DemoGenerationError` when ``max_consecutive_failures``
seeds in a row fail (planner or replay), so a task whose planner never succeeds cannot hang.
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import h5py

from l1flow_rl.config import TaskConfig
from l1flow_rl.experts.maniskill._plan_worker import ATTEMPT_MARK, NO_SOLUTION_EXIT, READY_MARK
from l1flow_rl.experts.maniskill.solutions import SOLUTION_TAGS
from l1flow_rl.experts.quality import check_quality
from l1flow_rl.experts.registry import DemoGenerationError

__all__ = ["dataset_path", "ensure_maniskill_demos"]

_BATCH = re.compile(r"seeds_(\d+)-(\d+)\.attempts\.json$")
#: Most seeds per worker process: big enough to amortise its ~10 s start, small enough to resume cheaply.
MAX_BATCH = 25
#: Fewest seeds worth a worker of their own (its start costs about as much as 10 PushCube demos).
MIN_BATCH = 8
#: Seconds a worker may take to start (imports, Vulkan) before its first seed.
WORKER_START_S = 240


@dataclass
class _Batch:
    first: int
    last: int
    attempts: list[dict]

    @property
    def stem(self) -> str:
        return f"seeds_{self.first:06d}-{self.last:06d}"

    @property
    def planned_seeds(self) -> list[int]:
        return [a["seed"] for a in self.attempts if a["success"]]


def _mode_name(task) -> str:
    return f"{task.obs_mode}.{task.control_mode}.{task.reward_mode}"


def _task_root(task, data_dir) -> Path:
    """The task's cache; plans of our own solution (``solutions.SOLUTION_TAGS``) apart from ManiSkill's."""
    tag = SOLUTION_TAGS.get(task.env_id)
    return Path(data_dir) / "maniskill" / (f"{task.env_id}.{tag}" if tag else task.env_id)


def dataset_path(task: TaskConfig, num: int, data_dir: str | os.PathLike, seed: int = 0) -> Path:
    """Where :func:`ensure_maniskill_demos` puts (or finds) ``num`` demonstrations of ``task``."""
    return _task_root(task, data_dir) / _mode_name(task) / f"{task.env_id}.seed{seed}.n{num}.h5"


def _check_task(task, num: int, max_consecutive_failures: int) -> None:
    if getattr(task, "simulator", "maniskill") != "maniskill":
        raise DemoGenerationError(
            f"task {task.name!r} runs on {task.simulator!r}; only ManiSkill tasks have offline "
            "demonstration makers"
        )
    if task.obs_mode not in ("state", "rgb"):
        raise DemoGenerationError(
            f"task {task.name!r}: obs_mode must be 'state' or 'rgb', got {task.obs_mode!r}"
        )
    if num < 1:
        raise DemoGenerationError(f"demos.num must be >= 1, got {num}")
    if max_consecutive_failures < 1:
        raise DemoGenerationError(
            f"demos.max_consecutive_failures must be >= 1, got {max_consecutive_failures}"
        )


@contextmanager
def _locked(directory: Path) -> Iterator[None]:
    # Two runs filling the same cache would both plan the same seeds; the second waits instead.
    directory.mkdir(parents=True, exist_ok=True)
    with open(directory / ".lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _write_json_atomic(path: Path, data) -> None:
    tmp = path.with_name(f".{path.name}.partial")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def _planned_chain(planned: Path, seed: int) -> list[_Batch]:
    """Finished planner batches that cover seeds seed, seed+1, ... without a gap."""
    batches = {}
    for file in planned.glob("seeds_*.attempts.json"):
        match = _BATCH.match(file.name)
        if match:
            batches[int(match.group(1))] = _Batch(
                int(match.group(1)), int(match.group(2)), json.loads(file.read_text())
            )
    chain, cur = [], seed
    while cur in batches:
        chain.append(batches[cur])
        cur = batches[cur].last + 1
    return chain


def _replayed_seeds(mode_dir: Path, batch: _Batch) -> list[int] | None:
    """Seeds whose replay succeeded, or None when the batch has not been replayed into this mode yet."""
    if not batch.planned_seeds:
        return []
    json_path = mode_dir / f"{batch.stem}.json"
    if not json_path.is_file():
        return None
    return [int(ep["episode_seed"]) for ep in json.loads(json_path.read_text())["episodes"]]


class _Worker:
    """One worker process; reads its attempt lines as they come, ends it at the deadline."""

    def __init__(self, args: list[str], log: Path, deadline_s: float, bar, stop: threading.Event) -> None:
        self.attempts: list[dict] = []
        self.ready = self.stopped = False
        self.log = log
        # one simulator per process gains nothing from intra-op threads; parallel workers would contend
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
        with open(log, "w") as log_file:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "l1flow_rl.experts.maniskill._plan_worker", *args],
                stdout=subprocess.PIPE,
                stderr=log_file,
                text=True,
                env=env,
                start_new_session=True,  # its own process group, so a timeout ends the whole worker
            )
        lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._pump, args=(lines,), daemon=True).start()
        deadline = time.monotonic() + deadline_s
        self.timed_out = False
        try:
            while True:
                try:
                    line = lines.get(timeout=max(0.0, min(1.0, deadline - time.monotonic())))
                except queue.Empty:
                    if stop.is_set():  # the run is being interrupted
                        self.stopped = True
                        self._kill()
                        break
                    if time.monotonic() >= deadline:
                        self.timed_out = True
                        self._kill()
                        break
                    continue
                if line is None:
                    break
                self.ready = self.ready or line == READY_MARK
                if line.startswith(ATTEMPT_MARK):
                    record = json.loads(line[len(ATTEMPT_MARK) :])
                    self.attempts.append(record)
                    if record["success"] and bar is not None and bar.n < bar.total:
                        bar.update(1)
            self.returncode = self.proc.wait()
        finally:
            self._kill()

    def _pump(self, lines: queue.Queue) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            lines.put(line.strip())
        lines.put(None)

    def _kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()

    def log_tail(self, lines: int = 15) -> str:
        text = self.log.read_text(errors="replace").replace("\r", "\n") if self.log.is_file() else ""
        kept = [ln for ln in text.splitlines() if ln.strip() and "it/s]" not in ln and "step/s]" not in ln]
        return "\n".join(kept[-lines:])


class _Generator:
    """Runs workers for one task and commits what they make into the cache."""

    def __init__(self, task, data_dir, attempt_timeout: int) -> None:
        self.task, self.attempt_timeout = task, attempt_timeout
        self.root = _task_root(task, data_dir)
        self.planned = self.root / "planned"
        self.mode_dir = self.root / _mode_name(task)
        self.tmp_root = self.root / ".work"
        self.stop = threading.Event()

    def _worker_args(self, work: Path) -> list[str]:
        t = self.task
        return [
            "--env-id", t.env_id, "--work-dir", str(work), "--attempt-timeout", str(self.attempt_timeout),
            "--obs-mode", t.obs_mode, "--control-mode", t.control_mode, "--reward-mode", t.reward_mode,
        ]  # fmt: skip

    def _fail(self, what: str, worker: _Worker) -> DemoGenerationError:
        reason = "timed out" if worker.timed_out else f"exited with code {worker.returncode}"
        return DemoGenerationError(
            f"{self.task.env_id}: {what}: the worker {reason}. Its log ends with:\n{worker.log_tail()}"
        )

    def _commit_replay(self, work: Path, batch: _Batch) -> None:
        produced = f"plan.{self.task.obs_mode}.{self.task.control_mode}.physx_cpu"  # the replay tool's naming
        self.mode_dir.mkdir(parents=True, exist_ok=True)
        os.replace(work / f"{produced}.h5", self.mode_dir / f"{batch.stem}.h5")
        os.replace(work / f"{produced}.json", self.mode_dir / f"{batch.stem}.json")  # json last: the marker

    def plan_batch(self, first: int, count: int, bar) -> None:
        work = self.tmp_root / f"plan_{first:06d}"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        args = [*self._worker_args(work), "--first-seed", str(first), "--num-seeds", str(count)]
        # per-attempt limit plus a replay allowance of 60 s per episode (an rgb replay renders every step)
        deadline = WORKER_START_S + count * (self.attempt_timeout + 60)
        worker = _Worker(args, work / "worker.log", deadline, bar, self.stop)
        if worker.stopped:
            return  # interrupted: nothing is committed, the seeds stay unplanned
        if worker.returncode == NO_SOLUTION_EXIT:
            raise DemoGenerationError(f"{self.task.env_id}: {worker.log_tail(3)}")
        planned_all = len(worker.attempts) == count
        self.planned.mkdir(parents=True, exist_ok=True)
        if not planned_all and not worker.ready:
            raise self._fail(f"planning seeds {first}.. failed before the first attempt", worker)
        if not planned_all:
            # The worker died on a seed (a planner crash): that seed failed, the batch's successes are
            # lost and its later seeds are skipped. The batch keeps its full range so that batches
            # planned beside it still join the chain without a gap.
            crashed = first + len(worker.attempts)
            attempts = [{**a, "success": False} for a in worker.attempts]
            attempts.append(
                {"seed": crashed, "success": False, "seconds": None, "error": "the worker crashed"}
            )
            attempts += [
                {"seed": s, "success": False, "seconds": None, "error": None, "skipped": True}
                for s in range(crashed + 1, first + count)
            ]
            _write_json_atomic(
                self.planned / f"{_Batch(first, first + count - 1, attempts).stem}.attempts.json", attempts
            )
            return
        batch = _Batch(first, first + count - 1, worker.attempts)
        for stale in [
            *self.planned.glob(f"seeds_{first:06d}-*"),
            *self.mode_dir.glob(f"seeds_{first:06d}-*"),
        ]:
            stale.unlink()  # an interrupted run's uncommitted batch (no attempts file: not in the chain)
        if batch.planned_seeds:
            os.replace(work / "plan.h5", self.planned / f"{batch.stem}.h5")
            os.replace(work / "plan.json", self.planned / f"{batch.stem}.json")
        _write_json_atomic(self.planned / f"{batch.stem}.attempts.json", batch.attempts)
        if worker.returncode != 0:
            # planning finished and is kept; the replay failed (e.g. a reward mode the task lacks)
            raise self._fail(f"replaying seeds {first}..{batch.last} into {_mode_name(self.task)}", worker)
        if batch.planned_seeds:
            self._commit_replay(work, batch)
        shutil.rmtree(work, ignore_errors=True)

    def replay_batch(self, batch: _Batch) -> None:
        """Replay an already planned batch into this task's modes (another obs/control mode than before)."""
        work = self.tmp_root / f"replay_{batch.first:06d}"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        for suffix in (".h5", ".json"):
            shutil.copyfile(self.planned / f"{batch.stem}{suffix}", work / f"plan{suffix}")
        deadline = WORKER_START_S + 60 * len(batch.planned_seeds)
        worker = _Worker(self._worker_args(work), work / "worker.log", deadline, None, self.stop)
        if worker.stopped:
            return
        if worker.returncode != 0:
            raise self._fail(f"replaying {batch.stem} into {_mode_name(self.task)}", worker)
        self._commit_replay(work, batch)
        shutil.rmtree(work, ignore_errors=True)

    def outcomes(self, chain: list[_Batch]) -> list[tuple[int, bool, str | None]]:
        """(seed, usable demo?, error) for every attempted seed, in seed order."""
        out = []
        for batch in chain:
            replayed = set(_replayed_seeds(self.mode_dir, batch) or [])
            for a in batch.attempts:
                if a.get("skipped"):
                    continue
                ok = a["seed"] in replayed
                if a["success"]:
                    error = None if ok else "the replay into the target mode failed"
                else:
                    error = a["error"]
                out.append((a["seed"], ok, error))
        return out

    def merge(self, chain: list[_Batch], num: int, target: Path) -> None:
        """Write the first ``num`` demonstrations (by seed) as one ManiSkill file pair, atomically."""
        tmp_h5 = target.with_name(f".{target.name}.partial")
        tmp_json = target.with_name(f".{target.stem}.json.partial")
        episodes, env_info = [], None
        with h5py.File(tmp_h5, "w") as out:
            for batch in chain:
                if not batch.planned_seeds or len(episodes) >= num:
                    continue
                meta = json.loads((self.mode_dir / f"{batch.stem}.json").read_text())
                env_info = env_info or meta["env_info"]
                with h5py.File(self.mode_dir / f"{batch.stem}.h5", "r") as src:
                    for ep in meta["episodes"]:
                        if len(episodes) >= num:
                            break
                        new_id = len(episodes)
                        src.copy(src[f"traj_{ep['episode_id']}"], out, f"traj_{new_id}")
                        episodes.append({**ep, "episode_id": new_id})
        info = {"env_info": env_info, "episodes": episodes, "source": "l1flow_rl.experts.maniskill.demos"}
        tmp_json.write_text(json.dumps(info, indent=1))
        os.replace(tmp_json, target.with_suffix(".json"))
        os.replace(tmp_h5, target)  # the h5 appears last: its presence means the pair is complete


def _batch_sizes(
    need: int, outcomes: list[tuple[int, bool, str | None]], failures_left: int, workers: int
) -> list[int]:
    """Seeds for the next round, split into up to ``workers`` batches of at least MIN_BATCH seeds."""
    good = sum(ok for _, ok, _ in outcomes)
    # success-rate estimate with a prior of 0.9 worth 2 seeds: most solutions succeed
    # and each extra seed costs a replay, while low rates correct themselves after one round
    rate = (good + 1.8) / (len(outcomes) + 2)
    total = max(1, min(math.ceil(need / max(rate, 0.05) * 1.1), failures_left, MAX_BATCH * workers))
    parts = max(1, min(workers, total // MIN_BATCH))
    base, extra = divmod(total, parts)
    return [base + (i < extra) for i in range(parts)]


def ensure_maniskill_demos(
    task: TaskConfig,
    num: int,
    data_dir: str | os.PathLike,
    seed: int = 0,
    max_consecutive_failures: int = 50,
    *,
    attempt_timeout: int = 120,
    workers: int | None = None,
    quality: str = "expert",
    progress: bool = True,
) -> Path:
    """Path of a ManiSkill file with ``num`` successful demonstrations of ``task``, generating only what
    the cache under ``data_dir`` lacks. Idempotent and resumable; see the module docstring.

    Args:
        task: the task config (``env_id``, ``obs_mode``, ``control_mode``, ``reward_mode``).
        num: demonstrations wanted.
        data_dir: cache root.
        seed: the first episode seed; seeds seed, seed+1, ... are tried in order.
        max_consecutive_failures: stop with :class:`DemoGenerationError` after this many failed
            seeds in a row.
        attempt_timeout: seconds one planner attempt may take before it counts as failed.
        workers: worker processes run side by side (default: the CPU count, at most 4); a round of
            fewer than 2 * MIN_BATCH seeds uses one.
        quality: ``mixed`` makes the expert file, then a labelled mixed-quality file beside it
            (``....n<N>.mixed.h5``; see :mod:`l1flow_rl.experts.quality` and
            :mod:`l1flow_rl.experts.maniskill._perturb_worker`); state tasks only.
        progress: show a tqdm bar of usable demonstrations.

    Example:
        >>> from l1flow_rl.config import load_task_config
        >>> path = ensure_maniskill_demos(load_task_config("maniskill_pushcube"), 3, "data")  # doctest: +SKIP
    """
    _check_task(task, num, max_consecutive_failures)
    check_quality(quality)
    if quality == "mixed" and task.obs_mode != "state":
        raise DemoGenerationError(f"task {task.name!r}: demos.quality=mixed needs obs_mode state")
    expert = _ensure_expert(
        task, num, data_dir, seed, max_consecutive_failures, attempt_timeout, workers, progress
    )
    if quality == "expert":
        return expert
    mixed = expert.with_name(f"{expert.stem}.mixed.h5")
    if mixed.is_file() and mixed.with_suffix(".json").is_file():
        return mixed
    cmd = [sys.executable, "-m", "l1flow_rl.experts.maniskill._perturb_worker", str(expert), str(mixed)]
    # perturbed episodes run longer than the expert's (pauses, a second grasp): twice the task's limit
    cmd += ["--seed", str(seed), "--max-steps", str(2 * task.max_episode_steps)]
    done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    if done.returncode != 0:
        raise DemoGenerationError(
            f"{task.env_id}: making the mixed-quality set from {expert} failed:\n{done.stderr[-3000:]}"
        )
    return mixed


def _ensure_expert(
    task, num, data_dir, seed, max_consecutive_failures, attempt_timeout, workers, progress
) -> Path:
    workers = workers or max(1, min(4, os.cpu_count() or 1))
    target = dataset_path(task, num, data_dir, seed)
    if target.is_file() and target.with_suffix(".json").is_file():
        return target
    gen = _Generator(task, data_dir, attempt_timeout)
    # optional dependency (app extra): the progress bar
    from tqdm import tqdm

    with (
        _locked(gen.root),
        tqdm(total=num, desc=f"{task.env_id} demos", unit="demo", disable=not progress) as bar,
    ):
        if target.is_file() and target.with_suffix(".json").is_file():
            return target  # made by a run that held the lock before us
        shutil.rmtree(gen.tmp_root, ignore_errors=True)  # leftovers of an interrupted run
        while True:
            chain = _planned_chain(gen.planned, seed)
            outcomes: list[tuple[int, bool, str | None]] = []
            for batch in chain:
                if sum(ok for _, ok, _ in outcomes) >= num:
                    break  # enough: later batches need no replay into this mode
                if _replayed_seeds(gen.mode_dir, batch) is None:
                    gen.replay_batch(batch)  # planned for another obs/control mode earlier
                outcomes += gen.outcomes([batch])
            have = sum(ok for _, ok, _ in outcomes)
            bar.n = min(have, num)
            bar.refresh()
            if have >= num:
                target.parent.mkdir(parents=True, exist_ok=True)
                gen.merge(chain, num, target)
                shutil.rmtree(gen.tmp_root, ignore_errors=True)
                return target
            streak = 0
            while streak < len(outcomes) and not outcomes[-1 - streak][1]:
                streak += 1
            if streak >= max_consecutive_failures:
                first_failed, last_error = outcomes[-streak][0], outcomes[-1][2]
                raise DemoGenerationError(
                    f"{task.env_id}: {streak} seeds in a row failed (seeds "
                    f"{first_failed}..{outcomes[-1][0]}, "
                    f"max_consecutive_failures={max_consecutive_failures}); {have}/{num} demonstrations "
                    f"made. Last error: {last_error}"
                )
            first = chain[-1].last + 1 if chain else seed
            sizes = _batch_sizes(num - have, outcomes, max_consecutive_failures - streak, workers)
            starts = [first + sum(sizes[:i]) for i in range(len(sizes))]
            with ThreadPoolExecutor(len(sizes)) as pool:  # each thread waits on its own worker process
                jobs = [pool.submit(gen.plan_batch, s, k, bar) for s, k in zip(starts, sizes)]
                try:
                    for job in jobs:
                        job.result()
                except BaseException:
                    gen.stop.set()  # end the other workers too; their batches are not committed
                    raise
