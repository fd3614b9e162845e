"""Shifted replays (``demos.shifted_replays``): new robosuite episodes made from a file's successful
ones by moving their approach and grasp to the object's position in a fresh scene
(:mod:`l1flow_rl.experts.object_shift`) and playing them open loop in the simulator; the played
episodes that succeed join the file, labelled ``shifted``.

Why: a 30-episode mixed Can set starts 3 of its episodes in the start bin's far quartile, and a policy
trained on it closes its grasp pulled toward the bin's centre there; BC on 100 episodes (22 far
starts) has no pull. Each attempt costs one
episode of env steps, counted in the file's ``shifted_replays`` attribute.

Attempt ``i`` resets the scene from seed ``SHIFT_SEEDS + 100_000 * seed + i``: apart from the
demonstration (0 on), validation (10,000 on), test (100,000 on) and online (1,000,000 on) seeds.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from l1flow_rl.config import TaskConfig
from l1flow_rl.envs.robosuite import sim
from l1flow_rl.envs.robosuite.pool import worker_pool
from l1flow_rl.experts.object_shift import shift_actions
from l1flow_rl.experts.quality import GripperLayout
from l1flow_rl.experts.registry import DemoGenerationError
from l1flow_rl.experts.robosuite.recording import record_episode
from l1flow_rl.experts.robosuite.scripted import CLOSED, OPEN, body_yaw

__all__ = [
    "SHIFTED_OBJECTS",
    "SHIFT_SEEDS",
    "ShiftedObject",
    "Source",
    "add_shifted_replays",
    "check_shifted_replays",
    "nearest_sources",
    "object_pose",
    "shifted_replay",
]

SHIFT_SEEDS = 50_000_000
MAX_ATTEMPTS = 100_000  # attempts per seed (the seed ranges of two file seeds must not meet)
#: steps the last action is held after a replay's actions end: a released can is still falling
SETTLE_STEPS = 40
#: a turning object's source is drawn among this many nearest in pose (MimicGen's nearest-neighbour
#: source selection, its default k and its metric: metres plus radians)
NEAREST_K = 3
_GRIP = GripperLayout("absolute", open=OPEN, closed=CLOSED)


@dataclasses.dataclass(frozen=True)
class ShiftedObject:
    """The grasped object of a task whose episodes can be shifted."""

    #: the object's MuJoCo body id in an env
    body: Callable
    #: the grasp depends on the object's yaw (a nut's handle): the approach turns with the object,
    #: and each attempt replays one of its ``NEAREST_K`` nearest sources in pose, so that the turn
    #: the carry has to undo stays small. A can grasps alike at any yaw: translation only, any source.
    turns: bool


SHIFTED_OBJECTS: dict[str, ShiftedObject] = {
    "PickPlaceCan": ShiftedObject(lambda env: env.obj_body_id["Can"], turns=False),
    "NutAssemblySquare": ShiftedObject(lambda env: env.obj_body_id[env.nuts[env.nut_id].name], turns=True),
}


@dataclasses.dataclass(frozen=True)
class Source:
    """A successful episode to replay: its name, first MuJoCo state, actions and the object's pose
    in its scene (position, yaw)."""

    name: str
    state: np.ndarray
    actions: np.ndarray
    position: np.ndarray
    yaw: float


def object_pose(env, env_id: str) -> tuple[np.ndarray, float]:
    """The shifted object's world position and yaw (radians about the vertical)."""
    body = SHIFTED_OBJECTS[env_id].body(env)
    return np.array(env.sim.data.body_xpos[body], dtype=np.float64), body_yaw(env, body)


def _wrap(angle: float) -> float:
    return float((angle + np.pi) % (2 * np.pi) - np.pi)


def read_source(env, env_id: str, name: str, state: np.ndarray, actions: np.ndarray) -> Source:
    """A :class:`Source` with the object's pose read from ``state`` (restored in ``env``)."""
    sim.restore_state(env, state)
    position, yaw = object_pose(env, env_id)
    return Source(name, state, np.asarray(actions), position, yaw)


def nearest_sources(sources: list[Source], position: np.ndarray, yaw: float) -> list[Source]:
    """The ``NEAREST_K`` sources nearest to the pose (metres of x, y plus radians of yaw), nearest
    first (ties: the earlier source)."""
    distance = [
        float(np.linalg.norm(s.position[:2] - position[:2])) + abs(_wrap(yaw - s.yaw)) for s in sources
    ]
    return [sources[i] for i in np.argsort(distance, kind="stable")[:NEAREST_K]]


def shifted_replay(env, task: TaskConfig, sources: list[Source], seed: int, draw: int) -> dict:
    """One of ``sources`` moved to the object's pose in the scene of ``seed`` and played there: the
    robomimic demo dict (``attrs``: success, the source, its x, y offset and turn). ``draw`` picks the
    source: its index for a translated object, its rank among the nearest for a turning one."""
    spec = SHIFTED_OBJECTS[task.env_id]
    sim.seed_episode(env, seed)
    raw = env.reset()  # reset's own observation: record_episode's first step needs it (see its docstring)
    position, yaw = object_pose(env, task.env_id)
    source = nearest_sources(sources, position, yaw)[draw] if spec.turns else sources[draw]
    offset = (position - source.position)[:2]
    turn = _wrap(yaw - source.yaw) if spec.turns else 0.0
    played = shift_actions(source.actions, offset, _GRIP, turn=turn, pivot=source.position[:2])
    queue = iter(np.concatenate([played, np.repeat(played[-1:], SETTLE_STEPS, 0)]))
    extra = int(np.random.default_rng([seed, 8]).integers(1, 4))
    demo = record_episode(
        env, raw, seed, lambda: next(queue, None), lambda: False, task.max_episode_steps, extra
    )
    demo["attrs"] = {**demo["attrs"], "source_demo": source.name, "offset_xy": offset.tolist()}
    if spec.turns:
        demo["attrs"]["turn"] = turn
    return demo


_WORKER: dict = {}


def _worker_init(task: TaskConfig, episodes: list[tuple[str, np.ndarray, np.ndarray]]) -> None:
    torch.set_num_threads(1)
    env = sim.make_from_env_args(sim.env_args_for_task(task, cameras=[]), source=task.name)
    # each source's pose is read once per worker, not once per attempt
    _WORKER.update(task=task, env=env, sources=[read_source(env, task.env_id, *e) for e in episodes])


def _worker_replay(index: int, seed: int, draw: int) -> tuple[int, dict]:
    return index, shifted_replay(_WORKER["env"], _WORKER["task"], _WORKER["sources"], seed, draw)


def check_shifted_replays(task: TaskConfig, attempts: int) -> None:
    """Refuse ``demos.shifted_replays=attempts`` for ``task`` before any episode is made: its object
    must be one :data:`SHIFTED_OBJECTS` names, and the count within 1 to ``MAX_ATTEMPTS``."""
    if task.env_id not in SHIFTED_OBJECTS:
        raise DemoGenerationError(
            f"demos.shifted_replays={attempts}: task {task.name!r} ({task.env_id}) names no object to "
            f"shift episodes to (tasks that do: {sorted(SHIFTED_OBJECTS)})"
        )
    if not 0 < attempts <= MAX_ATTEMPTS:
        raise DemoGenerationError(f"demos.shifted_replays={attempts}: expected 1 to {MAX_ATTEMPTS} attempts")


def add_shifted_replays(
    task: TaskConfig,
    base: Path,
    target: Path,
    attempts: int,
    *,
    seed: int = 0,
    workers: int = 2,
    progress: bool = True,
) -> Path:
    """``target``: ``base``'s episodes, then the successful ones of ``attempts`` shifted replays of
    its successful episodes (drawn by ``seed``: any source for a translated object, one of the
    nearest for a turning one), labelled ``shifted``
    (``mask/shifted``; every earlier mask kept). The file's ``data`` attribute ``shifted_replays``
    holds what they cost: attempts, successes, env steps of every attempt, seconds, and each failed
    attempt's seed, source and move."""
    # optional dependencies: h5py (robomimic files), tqdm (the app extra's progress bars)
    import h5py
    from tqdm import tqdm

    from l1flow_rl.data.formats.robomimic_writer import RobomimicWriter

    check_shifted_replays(task, attempts)
    with h5py.File(base, "r") as h5:
        data = h5["data"]
        names = sorted(data, key=lambda n: int(n.rsplit("_", 1)[1]))
        # the successful episodes are the sources; a replay needs only their first state and actions
        # (the base episodes themselves are copied whole below)
        episodes = [
            (n, data[n]["states"][0], data[n]["actions"][()])
            for n in names
            if data[n].attrs.get("success", True) and data[n]["rewards"][()].max() > 0
        ]
        masks = {k: [m.decode() for m in h5["mask"][k][()]] for k in h5.get("mask", {})}
        env_args = json.loads(h5["data"].attrs["env_args"])
        # the base file's own attributes go on (the writer sets env_args and total; ours is rewritten)
        data_attrs = {
            k: v for k, v in h5["data"].attrs.items() if k not in ("env_args", "total", "shifted_replays")
        }
    if not episodes:
        raise DemoGenerationError(f"{base}: no successful episode to make shifted replays from")
    spec = SHIFTED_OBJECTS[task.env_id]
    rng = np.random.default_rng([seed, 13])
    choices = min(NEAREST_K, len(episodes)) if spec.turns else len(episodes)
    jobs = [(i, SHIFT_SEEDS + 100_000 * seed + i, int(rng.integers(choices))) for i in range(attempts)]
    state_task = dataclasses.replace(task, obs_mode="state", cameras=[])
    played: list[dict | None] = [None] * attempts
    start = time.perf_counter()
    with worker_pool(workers, _worker_init, (state_task, episodes)) as pool:
        futures = [pool.submit(_worker_replay, *job) for job in jobs]
        for fut in tqdm(
            cf.as_completed(futures), total=attempts, desc="shifted replays", disable=not progress
        ):
            i, demo = fut.result()
            played[i] = demo
    kept = [d for d in played if d["attrs"]["success"]]
    stats = {
        "attempts": attempts,
        "successes": len(kept),
        "env_steps": int(sum(len(d["actions"]) for d in played)),
        "seconds": round(time.perf_counter() - start, 1),
        "seeds_from": SHIFT_SEEDS + 100_000 * seed,
        "source_episodes": len(episodes),
        # the attempts that did not succeed are not stored as episodes; what they were is kept here
        "failed": [
            {k: d["attrs"][k] for k in ("seed", "source_demo", "offset_xy", "turn") if k in d["attrs"]}
            for d in played
            if not d["attrs"]["success"]
        ],
    }
    with RobomimicWriter(target, env_args) as writer, h5py.File(base, "r") as h5:
        for name in names:  # verbatim: every dataset and attribute of the base episodes kept
            writer.copy(h5["data"][name])
        for key, value in data_attrs.items():
            writer.set_data_attr(key, value)
        added = [writer.add({**d, "attrs": {**d["attrs"], "quality": "shifted"}}) for d in kept]
        masks["train"] = [*masks.get("train", names), *added]
        masks["shifted"] = [*masks.get("shifted", []), *added]
        for name, members in masks.items():
            writer.add_mask(name, members)
        writer.set_data_attr("shifted_replays", json.dumps(stats))
    if progress:
        print(
            f"{task.env_id}: {len(kept)} of {attempts} shifted replays succeed ({stats['env_steps']} env "
            f"steps, {stats['seconds']:.0f} s)"
        )
    return target
