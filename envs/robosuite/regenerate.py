"""Observations of a robomimic/MimicGen file recomputed from its stored MuJoCo states.

robomimic's own ``dataset_states_to_obs.py`` needs ``mujoco_py`` through its env wrapper, which
robosuite 1.5 no longer uses; this does the same job on robosuite 1.5: for every demo, restore each
stored state (after loading the demo's ``model_file``), read robomimic's observation there (chosen
cameras rendered), and play the last action for the final ``next_obs``. Demos are spread over
worker processes, with a progress bar.

Every ``obs`` row and all ``next_obs`` rows but the last equal what the env produced when it
recorded them (observations are a function of the MuJoCo state here, see
:func:`l1flow_rl.envs.robosuite.sim.step`), except ``robot0_joint_acc``, which depends on the last
control input. The final ``next_obs`` row is close, not equal (about 1 cm for a moving arm): the
controllers' internal state (e.g. the gripper's ramped command) is not part of a stored state.

    python -m l1flow_rl.envs.robosuite.regenerate IN.hdf5 OUT.hdf5 --cameras agentview robot0_eye_in_hand
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np
import torch
from l1flow_rl.envs.robosuite import sim
from l1flow_rl.envs.robosuite.pool import worker_pool

from l1flow_rl.data.episodes import EpisodeDataError
from l1flow_rl.data.formats.base import open_h5
from l1flow_rl.data.formats.robomimic import check_replayable, demo_names
from l1flow_rl.data.formats.robomimic_writer import RobomimicWriter

__all__ = ["regenerate_observations", "replay_demo_observations"]

_WORKER: dict = {}


def _read_env_args(h5: h5py.File, path: Path) -> dict:
    raw = h5["data"].attrs.get("env_args") if "data" in h5 else None
    if raw is None:
        raise EpisodeDataError(f"{path}: key 'data' attribute 'env_args': missing; cannot rebuild the scene")
    try:
        return json.loads(raw)
    except (TypeError, ValueError) as err:
        raise EpisodeDataError(f"{path}: key 'data' attribute 'env_args': not JSON ({err})") from err


def replay_demo_observations(
    env, states: np.ndarray, actions: np.ndarray, model_file: str | None, cameras: Sequence[str]
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(obs, next_obs) of one demo, robomimic's keys -> [T, ...], from its states on ``env``."""
    current = getattr(env, "_l1flow_model_file", None)
    frames = []
    for t, state in enumerate(states):
        reload = model_file if t == 0 and model_file is not None and model_file != current else None
        frames.append(sim.robomimic_obs(sim.restore_state(env, state, reload), cameras))
    env._l1flow_model_file = model_file if model_file is not None else current
    raw, _ = sim.step(env, actions[-1])  # the final next_obs
    frames.append(sim.robomimic_obs(raw, cameras))
    keys = frames[0].keys()
    obs = {k: np.stack([f[k] for f in frames[:-1]]) for k in keys}
    next_obs = {k: np.stack([f[k] for f in frames[1:]]) for k in keys}
    return obs, next_obs


def _worker_init(env_args: dict, cameras: list[str], image_size: int | None, source: str) -> None:
    torch.set_num_threads(1)
    _WORKER["env"] = sim.make_from_env_args(env_args, cameras=cameras, image_size=image_size, source=source)
    _WORKER["cameras"] = cameras
    _WORKER["source"] = source


def _worker_demo(name: str) -> tuple[str, dict, dict]:
    with h5py.File(_WORKER["source"], "r") as h5:
        group = h5["data"][name]
        states, actions = group["states"][()], group["actions"][()]
        model_file = group.attrs.get("model_file")
    if isinstance(model_file, bytes):
        model_file = model_file.decode()
    obs, next_obs = replay_demo_observations(_WORKER["env"], states, actions, model_file, _WORKER["cameras"])
    return name, obs, next_obs


def _check_demo(h5: h5py.File, path: Path, name: str, action_dim: int | None) -> None:
    check_replayable(h5["data"][name], path, name, action_dim)


def regenerate_observations(
    source: str | os.PathLike,
    target: str | os.PathLike,
    *,
    cameras: Sequence[str] | None = None,
    image_size: int | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> Path:
    """Write ``target``: ``source``'s demos (states, actions, rewards, dones, attributes) with
    ``obs``/``next_obs`` recomputed from the states; images of ``cameras`` (default: the file's
    recorded ``camera_names`` when it rendered any, else none) at ``image_size``. Every demo is
    checked (states present, one per action, finite) before any replay starts."""
    from tqdm import tqdm  # optional dependency (the app extra): the progress bar

    source, target = Path(source), Path(target)
    with open_h5(source) as h5:
        env_args = _read_env_args(h5, source)
        names = demo_names(h5, source)
        for name in names:
            _check_demo(h5, source, name, None)
        masks = {k: [m.decode() for m in h5["mask"][k][()]] for k in h5["mask"]} if "mask" in h5 else {}
    kwargs = env_args.get("env_kwargs", {})
    if cameras is None:
        cameras = list(kwargs.get("camera_names", [])) if kwargs.get("use_camera_obs") else []
    cameras = list(cameras)
    out_args = json.loads(json.dumps(env_args))
    out_kwargs = out_args.setdefault("env_kwargs", {})
    out_kwargs.update(
        use_camera_obs=bool(cameras), camera_names=cameras or out_kwargs.get("camera_names", [])
    )
    if image_size is not None:
        out_kwargs["camera_heights"] = out_kwargs["camera_widths"] = int(image_size)
    workers = max(1, min(workers or min(2, os.cpu_count() or 1), len(names)))
    initargs = (env_args, cameras, image_size, str(source))
    bar = tqdm(total=len(names), desc=f"regenerating {source.name}", unit="demo", disable=not progress)
    with (
        worker_pool(workers, _worker_init, initargs) as pool,
        RobomimicWriter(target, out_args) as writer,
        h5py.File(source, "r") as h5,
    ):
        for name, obs, next_obs in pool.map(_worker_demo, names):
            group = h5["data"][name]
            demo = {key: group[key][()] for key in ("states", "actions", "rewards", "dones")}
            attrs = {k: v for k, v in group.attrs.items() if k not in ("num_samples", "model_file")}
            writer.add(
                {
                    **demo,
                    "obs": obs,
                    "next_obs": next_obs,
                    "model_file": group.attrs["model_file"],
                    "attrs": attrs,
                },
                name=name,
            )
            bar.update(1)
        for mask, members in masks.items():
            writer.add_mask(mask, members)
    bar.close()
    return target


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", help="robomimic/MimicGen .hdf5 with states (observations optional)")
    parser.add_argument("target", help="the .hdf5 to write")
    parser.add_argument("--cameras", nargs="*", default=None, help="cameras to render (default: the file's)")
    parser.add_argument("--image-size", type=int, default=None)
    parser.add_argument("--workers", type=int, default=None)
    args = parser.parse_args(argv)
    path = regenerate_observations(
        args.source, args.target, cameras=args.cameras, image_size=args.image_size, workers=args.workers
    )
    print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
