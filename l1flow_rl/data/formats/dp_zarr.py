"""Diffusion Policy's zarr replay buffer (e.g. ``pusht_cchi_v7_replay.zarr``).

``data/<key>`` arrays hold every step of every episode back to back; ``meta/episode_ends`` holds the
exclusive end row of each episode. Diffusion Policy's format has no rewards, done flags or final
observation: ``("next", "reward")`` is 0 (metadata ``has_rewards=False``), ``("next", "done")`` marks
each episode's last step, which counts as truncated, and the last observation stands in for the
final one (``has_final_observation=False``). Files written by this project's PushT expert add what
Diffusion Policy's readers ignore: ``data/reward`` (read as the reward), ``meta/terminated`` (which
episodes ended in success) and root attributes (``env_id``, ``control_mode``). PushT's actions are
absolute targets (``control="absolute"``). Images (``data/img``, float values in [0, 255] in
Diffusion Policy's files, uint8 in this project's) become uint8 ``"rgb"``.

``state_keys`` may name ``agent_pos``: ``data/agent_pos`` when the file has it, else the first two
columns of ``data/state``, as Diffusion Policy's PushT datasets derive it (its keypoint task's
observation is ``keypoint`` then ``agent_pos``; its image task's is the image and ``agent_pos``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
from tensordict import TensorDict

from l1flow_rl.data.episodes import (
    EpisodeDataError,
    as_tensor,
    assemble_episode,
    check_finite,
    to_uint8_image,
    where,
)
from l1flow_rl.data.formats.base import EpisodeFile

__all__ = ["DiffusionPolicyZarr"]


class DiffusionPolicyZarr(EpisodeFile):
    """Reader for a Diffusion Policy zarr replay buffer (zarr v2 or v3 store).

    Args:
        path: the ``.zarr`` directory.
        state_keys: ``data/<key>`` arrays concatenated into the state (default ``("state",)``).
        image_key: the ``data/<key>`` images for ``"rgb"``; ``"auto"`` uses ``img`` when present,
            ``None`` makes a state-only observation.
        action_key: the ``data/<key>`` array of actions.
    """

    format_name = "diffusion_policy_zarr"

    def __init__(
        self,
        path: Path,
        *,
        state_keys: Sequence[str] = ("state",),
        image_key: str | None = "auto",
        action_key: str = "action",
    ) -> None:
        super().__init__(path)
        # optional dependency (pusht extra): Diffusion Policy's zarr stores
        import zarr

        try:
            root = zarr.open_group(str(path), mode="r")
        except (FileNotFoundError, ValueError, OSError) as err:
            raise EpisodeDataError(f"{path}: cannot open as a zarr group: {err}") from err
        for group in ("data", "meta"):
            if group not in root:
                raise EpisodeDataError(
                    f"{where(path, key=group)}: missing; not a Diffusion Policy replay buffer"
                )
        self.data = root["data"]
        if image_key == "auto":
            image_key = "img" if "img" in self.data else None
        self.state_keys, self.image_key, self.action_key = list(state_keys), image_key, action_key
        self._derived = {}
        if "agent_pos" in self.state_keys and "agent_pos" not in self.data and "state" in self.data:
            self._derived["agent_pos"] = ("state", slice(0, 2))  # Diffusion Policy's convention
        arrays = [self._source(k) for k in self.state_keys]
        for key in [*arrays, action_key, *([image_key] if image_key else [])]:
            if key not in self.data:
                raise EpisodeDataError(
                    f"{where(path, key=f'data/{key}')}: missing (has {sorted(self.data.keys())})"
                )
        if "episode_ends" not in root["meta"]:
            raise EpisodeDataError(f"{where(path, key='meta/episode_ends')}: missing")
        ends = as_tensor(root["meta"]["episode_ends"][:], path, None, "meta/episode_ends").long().reshape(-1)
        if ends.numel() == 0:
            raise EpisodeDataError(f"{where(path, key='meta/episode_ends')}: no episodes")
        starts = torch.cat([torch.zeros(1, dtype=torch.long), ends[:-1]])
        empty = (ends <= starts).nonzero()
        if empty.numel():
            raise EpisodeDataError(
                f"{where(path, int(empty[0]), 'meta/episode_ends')}: the episode has no steps (ends must "
                "increase)"
            )
        self.reward_key = "reward" if "reward" in self.data else None
        for key in [
            *arrays,
            action_key,
            *([image_key] if image_key else []),
            *([self.reward_key] if self.reward_key else []),
        ]:
            rows = self.data[key].shape[0]
            if rows != int(ends[-1]):
                raise EpisodeDataError(
                    f"{where(path, ends.numel() - 1, f'data/{key}')}: has {rows} rows but meta/episode_ends "
                    f"ends at {int(ends[-1])} (truncated or mismatched arrays)"
                )
        self.starts, self.ends = starts.tolist(), ends.tolist()
        self.terminated = [False] * len(self.ends)
        if "terminated" in root["meta"]:
            flags = as_tensor(root["meta"]["terminated"][:], path, None, "meta/terminated").reshape(-1)
            if flags.numel() != len(self.ends):
                raise EpisodeDataError(
                    f"{where(path, key='meta/terminated')}: has {flags.numel()} entries for {len(self.ends)} "
                    "episodes (meta/episode_ends)"
                )
            self.terminated = flags.bool().tolist()
        self.attrs = dict(root.attrs)

    def _source(self, key: str) -> str:
        return self._derived.get(key, (key, None))[0]

    @property
    def metadata(self) -> dict:
        return {
            **super().metadata,
            "control": "absolute",  # Diffusion Policy's zarr datasets (PushT, robomimic abs) use targets
            **{k: self.attrs[k] for k in ("env_id", "control_mode") if isinstance(self.attrs.get(k), str)},
            "has_rewards": self.reward_key is not None,
            "has_final_observation": False,
        }

    def episode_ids(self) -> list[int]:
        return list(range(len(self.ends)))

    def episode_length(self, episode: int) -> int:
        return self.ends[episode] - self.starts[episode]

    def _read(self, episode: int, key: str) -> torch.Tensor:
        rows = slice(self.starts[episode], self.ends[episode])
        try:
            value = self.data[key][rows]
        except (OSError, ValueError, KeyError) as err:  # a missing or corrupt chunk
            raise EpisodeDataError(
                f"{where(self.path, episode, f'data/{key}')}: cannot be read ({err})"
            ) from err
        return as_tensor(value, self.path, episode, f"data/{key}")

    def _column(self, episode: int, key: str, steps: int) -> torch.Tensor:
        source, columns = self._derived.get(key, (key, None))
        value = self._read(episode, source).float().reshape(steps, -1)
        value = value[:, columns] if columns is not None else value
        return check_finite(value, self.path, episode, f"data/{source}")

    def read_episode(self, episode: int) -> TensorDict:
        actions = self._read(episode, self.action_key).float()
        steps = actions.shape[0]
        actions = check_finite(actions.reshape(steps, -1), self.path, episode, f"data/{self.action_key}")
        columns = [self._column(episode, k, steps) for k in self.state_keys]
        state = torch.cat(columns, dim=-1) if columns else torch.zeros(steps, 0)
        observation: torch.Tensor | dict = state
        if self.image_key is not None:
            key = f"data/{self.image_key}"
            rgb = to_uint8_image(
                self._read(episode, self.image_key), self.path, episode, key, channels_last=True
            )
            observation = {"state": state, "rgb": rgb}
        reward = None
        if self.reward_key is not None:
            reward = self._read(episode, self.reward_key).float()
            reward = check_finite(reward.reshape(steps), self.path, episode, f"data/{self.reward_key}")
        return assemble_episode(
            episode, observation, actions, reward=reward, terminated=self.terminated[episode]
        )
