"""robomimic / robosuite ``.hdf5``: ``data/demo_<i>/{obs/<key>, actions, rewards, dones}``.

Low-dimensional ``obs`` entries are concatenated into ``"state"`` (in ``state_keys`` order, default:
every non-image key in the file's order, which h5py gives alphabetically); one camera (``*_image``
key) becomes ``"rgb"``, or, with ``cameras``, each listed camera key becomes an entry of that name
(robosuite tasks: ``"agentview_image"``, ...). The last row of ``next_obs`` (when the file has it) is
the final observation; the controller config in ``env_args`` tells delta from absolute control and
the controller type (``control_mode``: ``OSC_POSE``, ...).

Shapes are checked when the file is opened (every demo's actions have the width the recorded
controller takes, and the same width), so a malformed file fails before anything is read. A file
without observations (robomimic's ``states``-only layout) is refused with the command that rebuilds
them; :func:`check_replayable` checks what a replay from the stored states needs.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path

import torch
from tensordict import TensorDict

from l1flow_rl.data.episodes import (
    EpisodeDataError,
    as_tensor,
    assemble_episode,
    check_finite,
    check_steps,
    to_uint8_image,
    where,
)
from l1flow_rl.data.formats.base import EpisodeFile, open_h5

__all__ = ["RobomimicFile", "check_replayable", "demo_names", "expected_action_dim", "has_observations"]

_DEMO = re.compile(r"demo_(\d+)$")


class RobomimicFile(EpisodeFile):
    """Reader for a robomimic-style hdf5 file.

    Args:
        path: the ``.hdf5`` file.
        state_keys: ``obs`` entries concatenated into the state, in order; default every non-image key.
        image_key: the camera for ``"rgb"``; ``"auto"`` takes the only ``*_image`` key when there is
            exactly one, ``None`` makes a state-only observation.
        cameras: image keys (``"agentview_image"``, ...) that each become an observation entry of
            that name beside ``"state"``; replaces ``image_key``.
    """

    format_name = "robomimic"

    def __init__(
        self,
        path: Path,
        *,
        state_keys: Sequence[str] | None = None,
        image_key: str | None = "auto",
        cameras: Sequence[str] | None = None,
    ) -> None:
        super().__init__(path)
        self.h5 = open_h5(path)
        try:
            self._open(state_keys, image_key, cameras)
        except BaseException:
            self.h5.close()
            raise

    def _open(self, state_keys: Sequence[str] | None, image_key: str | None, cameras: Sequence[str] | None):
        path = self.path
        self.demos = {int(_DEMO.match(n).group(1)): n for n in demo_names(self.h5, path)}
        self.env_args = _env_args(self.h5, path)
        first_id = next(iter(self.demos))
        first = self._group(first_id)
        if "obs" not in first:
            raise EpisodeDataError(
                f"{where(path, self.demos[first_id], 'obs')}: missing: the file stores no observations "
                f"(robomimic's states-only layout); rebuild them from the states with `python -m "
                f"l1flow_rl.envs.robosuite.regenerate {path} OUT.hdf5 [--cameras ...]` (training a robosuite "
                "task with data.path does this itself)"
            )
        keys = list(first["obs"].keys())
        images = [k for k in keys if k.endswith("_image")]
        self.cameras = list(cameras) if cameras else []
        if self.cameras:
            image_key = None
            for camera in self.cameras:
                if camera not in images:
                    raise EpisodeDataError(
                        f"{where(path, self.demos[first_id], f'obs/{camera}')}: missing; the file's images "
                        f"are {images} (regenerate the observations with that camera)"
                    )
        elif image_key == "auto":
            if len(images) > 1:
                raise EpisodeDataError(
                    f"{path}: several cameras {images}; pass image_key=<one of them> (or None for state only)"
                )
            image_key = images[0] if images else None
        self.image_key = image_key
        self.state_keys = list(state_keys) if state_keys is not None else [k for k in keys if k not in images]
        for key in self.state_keys:
            if key not in first["obs"]:
                raise EpisodeDataError(
                    f"{where(path, self.demos[first_id], f'obs/{key}')}: missing (state_keys); the file's "
                    f"low-dimensional keys are {[k for k in keys if k not in images]}"
                )
        self._check_action_widths()

    def _check_action_widths(self) -> None:
        """Every demo's actions are [T, A] with the A of the recorded controller (or, without one,
        of the first demo): checked from the shapes alone, before any data is read."""
        expected = expected_action_dim(self.env_args)
        source = "the recorded controller (env_args)"
        for episode, name in self.demos.items():
            shape = self._dataset(episode, "actions").shape
            if len(shape) != 2 or shape[0] == 0:
                raise EpisodeDataError(
                    f"{where(self.path, name, 'actions')}: expected [T >= 1, A], got {tuple(shape)}"
                )
            if expected is None:
                expected, source = shape[1], f"demo {name}"
            if shape[1] != expected:
                raise EpisodeDataError(
                    f"{where(self.path, name, 'actions')}: {shape[1]} action dims, but {source} takes "
                    f"{expected}"
                )

    @property
    def metadata(self) -> dict:
        return {
            **super().metadata,
            "env_id": self.env_args.get("env_name"),
            "control_mode": _controller_type(self.env_args),
            "control": _control(self.env_args),
            "has_rewards": True,  # read_episode requires them
            "has_final_observation": all(self._has_next_obs(e) for e in self.demos),
        }

    def _has_next_obs(self, episode: int) -> bool:
        group = self._group(episode)
        keys = [*self.state_keys, *([self.image_key] if self.image_key else []), *self.cameras]
        return "next_obs" in group and all(k in group["next_obs"] for k in keys)

    def _final_observation(self, episode: int, steps: int, name: str):
        """The last ``next_obs`` row, shaped like one observation; None when the file has none."""
        if not self._has_next_obs(episode):
            return None
        columns = []
        for key in self.state_keys:
            value = self._read(episode, f"next_obs/{key}")
            value = check_steps(value, steps, self.path, name, f"next_obs/{key}")[-1:]
            columns.append(check_finite(value.float().reshape(1, -1), self.path, name, f"next_obs/{key}"))
        state = torch.cat(columns, dim=-1)[0] if columns else torch.zeros(0)
        if self.image_key is None and not self.cameras:
            return state
        images = self._images(episode, steps, name, "next_obs", last=True)
        return {"state": state, **{k: v[0] for k, v in images.items()}}

    def _images(self, episode: int, steps: int, name: str, group: str, last: bool = False) -> dict:
        """Entry name -> uint8 [T (or 1), 3, H, W] of the selected camera(s)."""
        entries = {camera: camera for camera in self.cameras}
        if self.image_key is not None:
            entries = {"rgb": self.image_key}
        out = {}
        for entry, camera in entries.items():
            key = f"{group}/{camera}"
            rgb = check_steps(self._read(episode, key), steps, self.path, name, key)
            out[entry] = to_uint8_image(rgb[-1:] if last else rgb, self.path, name, key, channels_last=True)
        return out

    def _group(self, episode: int):
        return self.h5["data"][self.demos[episode]]

    def episode_ids(self) -> list[int]:
        return list(self.demos)

    def _dataset(self, episode: int, key: str):
        group = self._group(episode)
        if key not in group:
            raise EpisodeDataError(
                f"{where(self.path, self.demos[episode], key)}: missing (has {sorted(group)})"
            )
        return group[key]

    def episode_length(self, episode: int) -> int:
        return self._dataset(episode, "actions").shape[0]

    def episode_labels(self) -> dict[int, str] | None:
        """Each demo's ``quality`` attribute (written with robomimic's ``mask/<label>`` filter
        keys); None when no demo has one."""
        labels = {e: self._group(e).attrs.get("quality") for e in self.demos}
        if all(v is None for v in labels.values()):
            return None
        missing = [self.demos[e] for e, v in labels.items() if v is None]
        if missing:
            raise EpisodeDataError(
                f"{where(self.path, missing[0], 'quality')}: missing, while other demos carry a quality "
                f"label ({len(missing)} demos lack one)"
            )
        return {e: v.decode() if isinstance(v, bytes) else str(v) for e, v in labels.items()}

    def _read(self, episode: int, key: str) -> torch.Tensor:
        return as_tensor(self._dataset(episode, key)[()], self.path, self.demos[episode], key)

    def read_episode(self, episode: int) -> TensorDict:
        name = self.demos[episode]
        actions = self._read(episode, "actions")
        if actions.dim() != 2 or actions.shape[0] == 0:
            raise EpisodeDataError(
                f"{where(self.path, name, 'actions')}: expected [T >= 1, A], got {tuple(actions.shape)}"
            )
        steps = actions.shape[0]
        check_finite(actions, self.path, name, "actions")
        columns = []
        for key in self.state_keys:
            value = check_steps(self._read(episode, f"obs/{key}"), steps, self.path, name, f"obs/{key}")
            columns.append(check_finite(value.float().reshape(steps, -1), self.path, name, f"obs/{key}"))
        if not columns and self.image_key is None and not self.cameras:
            raise EpisodeDataError(f"{where(self.path, name, 'obs')}: no observation entries selected")
        state = torch.cat(columns, dim=-1) if columns else torch.zeros(steps, 0)
        observation: torch.Tensor | dict = state
        if self.image_key is not None or self.cameras:
            observation = {"state": state, **self._images(episode, steps, name, "obs")}
        reward = check_finite(
            check_steps(self._read(episode, "rewards"), steps, self.path, name, "rewards"),
            self.path,
            name,
            "rewards",
        )
        dones = check_steps(self._read(episode, "dones"), steps, self.path, name, "dones")
        return assemble_episode(
            episode,
            observation,
            actions,
            reward=reward,
            terminated=bool(dones[-1]),
            final_observation=self._final_observation(episode, steps, name),
        )

    def close(self) -> None:
        self.h5.close()


def _control(env_args: dict) -> str | None:
    """delta/absolute from robosuite's controller config (``control_delta`` up to robosuite 1.4, the
    arm parts' ``input_type`` from 1.5); None when the file does not say."""
    config = (env_args.get("env_kwargs") or {}).get("controller_configs") or {}
    if "control_delta" in config:
        return "delta" if config["control_delta"] else "absolute"
    kinds = {
        part.get("input_type")
        for part in (config.get("body_parts") or {}).values()
        if isinstance(part, dict) and part.get("input_type") in ("delta", "absolute")
    }
    return kinds.pop() if len(kinds) == 1 else None


# -- file-level helpers (also used by the robosuite replay tools) -------------------------------------


def demo_names(h5, path: Path) -> list[str]:
    """The ``data/demo_<i>`` group names in index order; errors name the file."""
    if "data" not in h5:
        raise EpisodeDataError(f"{where(path, key='data')}: missing; not a robomimic file")
    found = {int(m.group(1)): n for n in h5["data"] if (m := _DEMO.match(n))}
    if not found:
        raise EpisodeDataError(f"{where(path, key='data')}: has no demo_<i> groups")
    return [found[i] for i in sorted(found)]


def _env_args(h5, path: Path) -> dict:
    raw = h5["data"].attrs.get("env_args")
    if raw is None:
        return {}
    try:
        value = json.loads(raw)
    except (TypeError, ValueError) as err:
        raise EpisodeDataError(
            f"{where(path, key='data')}: attribute 'env_args' is not JSON ({err})"
        ) from err
    if not isinstance(value, dict):
        raise EpisodeDataError(f"{where(path, key='data')}: attribute 'env_args' is not a JSON object")
    return value


def has_observations(path: Path, keys: Sequence[str] = ()) -> bool:
    """Whether every demo of a robomimic file stores ``obs`` (with ``keys``, when given)."""
    with open_h5(path) as h5:
        for name in demo_names(h5, path):
            group = h5["data"][name]
            if "obs" not in group or any(k not in group["obs"] for k in keys):
                return False
    return True


def _arm_parts(config: dict) -> list[dict]:
    if "body_parts" in config:
        return [p for p in config["body_parts"].values() if isinstance(p, dict) and "input_type" in p]
    return [config] if config else []


def _controller_type(env_args: dict) -> str | None:
    """The arm controller robosuite ran (``OSC_POSE``, ...), None when the file does not say."""
    config = (env_args.get("env_kwargs") or {}).get("controller_configs") or {}
    kinds = {part.get("type") for part in _arm_parts(config)}
    return kinds.pop() if len(kinds) == 1 else None


#: arm action dims of robosuite's arm controllers (the gripper adds one per arm)
_ARM_DIMS = {"OSC_POSE": 6, "OSC_POSITION": 3, "IK_POSE": 6}


def expected_action_dim(env_args: dict) -> int | None:
    """The action width the recorded robosuite controller takes (arm dims + 1 gripper dim per
    robot), None when ``env_args`` does not say enough to know."""
    kwargs = env_args.get("env_kwargs") or {}
    arm = _ARM_DIMS.get(_controller_type(env_args) or "")
    robots = kwargs.get("robots")
    if arm is None or not robots:
        return None
    count = 1 if isinstance(robots, str) else len(robots)
    if env_args.get("env_name") == "TwoArmTransport" or count > 1:
        count = max(count, 2)
    return count * (arm + 1)


def check_replayable(group, path: Path, name: str, action_dim: int | None = None) -> None:
    """What replaying a demo from its stored states needs: ``states`` [T, S] and ``actions`` [T, A]
    present, one state per action, finite, ``A == action_dim`` when given, and a ``model_file``."""
    for key in ("states", "actions"):
        if key not in group:
            raise EpisodeDataError(f"{where(path, name, key)}: missing (has {sorted(group)})")
    states = as_tensor(group["states"][()], path, name, "states")
    actions = as_tensor(group["actions"][()], path, name, "actions")
    if states.dim() != 2 or actions.dim() != 2 or states.shape[0] != actions.shape[0] or states.shape[0] == 0:
        raise EpisodeDataError(
            f"{where(path, name, 'states')}: expected one flattened MuJoCo state per action, [T, S] with T = "
            f"{actions.shape[0] if actions.dim() else '?'}; got states {tuple(states.shape)}, "
            f"actions {tuple(actions.shape)}"
        )
    if action_dim is not None and actions.shape[1] != action_dim:
        raise EpisodeDataError(
            f"{where(path, name, 'actions')}: {actions.shape[1]} action dims, expected {action_dim}"
        )
    check_finite(states, path, name, "states")
    check_finite(actions, path, name, "actions")
    if "model_file" not in group.attrs:
        raise EpisodeDataError(f"{where(path, name, 'model_file')}: attribute missing (the scene's MJCF XML)")
