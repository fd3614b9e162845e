"""robomimic / robosuite ``.hdf5``: ``data/demo_<i>/{obs/<key>, actions, rewards, dones}``.

Low-dimensional ``obs`` entries are concatenated into ``"state"`` (in ``state_keys`` order, default:
every non-image key in the file's order, which h5py gives alphabetically); one camera (``*_image``
key) becomes ``"rgb"``. The last row of ``next_obs`` (when the file has it) is the final observation;
the controller config in ``env_args`` tells delta from absolute control.
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

__all__ = ["RobomimicFile"]

_DEMO = re.compile(r"demo_(\d+)$")


class RobomimicFile(EpisodeFile):
    """Reader for a robomimic-style hdf5 file.

    Args:
        path: the ``.hdf5`` file.
        state_keys: ``obs`` entries concatenated into the state, in order; default every non-image key.
        image_key: the camera for ``"rgb"``; ``"auto"`` takes the only ``*_image`` key when there is
            exactly one, ``None`` makes a state-only observation.
    """

    format_name = "robomimic"

    def __init__(
        self, path: Path, *, state_keys: Sequence[str] | None = None, image_key: str | None = "auto"
    ) -> None:
        super().__init__(path)
        self.h5 = open_h5(path)
        if "data" not in self.h5:
            raise EpisodeDataError(f"{where(path, key='data')}: missing; not a robomimic file")
        demos = {}
        for name in self.h5["data"]:
            match = _DEMO.match(name)
            if match:
                demos[int(match.group(1))] = name
        if not demos:
            raise EpisodeDataError(f"{where(path, key='data')}: has no demo_<i> groups")
        self.demos = dict(sorted(demos.items()))
        first = self._group(next(iter(self.demos)))
        if "obs" not in first:
            raise EpisodeDataError(f"{where(path, next(iter(self.demos)), 'obs')}: missing")
        keys = list(first["obs"].keys())
        images = [k for k in keys if k.endswith("_image")]
        if image_key == "auto":
            if len(images) > 1:
                raise EpisodeDataError(
                    f"{path}: several cameras {images}; pass image_key=<one of them> (or None for state only)"
                )
            image_key = images[0] if images else None
        self.image_key = image_key
        self.state_keys = list(state_keys) if state_keys is not None else [k for k in keys if k not in images]
        env_args = self.h5["data"].attrs.get("env_args")
        self.env_args = json.loads(env_args) if isinstance(env_args, (str, bytes)) else {}

    @property
    def metadata(self) -> dict:
        return {
            **super().metadata,
            "env_id": self.env_args.get("env_name"),
            "control_mode": None,
            "control": _control(self.env_args),
            "has_rewards": True,  # read_episode requires them
            "has_final_observation": all(self._has_next_obs(e) for e in self.demos),
        }

    def _has_next_obs(self, episode: int) -> bool:
        group = self._group(episode)
        keys = [*self.state_keys, *([self.image_key] if self.image_key else [])]
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
        if self.image_key is None:
            return state
        key = f"next_obs/{self.image_key}"
        rgb = check_steps(self._read(episode, key), steps, self.path, name, key)[-1:]
        return {"state": state, "rgb": to_uint8_image(rgb, self.path, name, key, channels_last=True)[0]}

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
        if not columns and self.image_key is None:
            raise EpisodeDataError(f"{where(self.path, name, 'obs')}: no observation entries selected")
        state = torch.cat(columns, dim=-1) if columns else torch.zeros(steps, 0)
        observation: torch.Tensor | dict = state
        if self.image_key is not None:
            key = f"obs/{self.image_key}"
            rgb = check_steps(self._read(episode, key), steps, self.path, name, key)
            observation = {
                "state": state,
                "rgb": to_uint8_image(rgb, self.path, name, key, channels_last=True),
            }
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
