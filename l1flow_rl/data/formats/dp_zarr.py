"""Diffusion Policy's zarr replay buffer (e.g. ``pusht_cchi_v7_replay.zarr``).

``data/<key>`` arrays hold every step of every episode back to back; ``meta/episode_ends`` holds the
exclusive end row of each episode. The format has no rewards, done flags or final observation:
``("next", "reward")`` is 0 (metadata ``has_rewards=False``), ``("next", "done")`` marks each
episode's last step, which counts as truncated, and the last observation stands in for the final one
(``has_final_observation=False``). PushT's actions are absolute targets (``control="absolute"``).
Images (``data/img``, float values in [0, 255] in Diffusion Policy's files) become uint8 ``"rgb"``.
Note that Diffusion Policy's PushT image policy feeds only the agent position (``state[:, :2]``) next
to the image; the default here keeps the whole ``data/state``.
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
        for key in [*self.state_keys, action_key, *([image_key] if image_key else [])]:
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
        for key in [*self.state_keys, action_key, *([image_key] if image_key else [])]:
            rows = self.data[key].shape[0]
            if rows != int(ends[-1]):
                raise EpisodeDataError(
                    f"{where(path, ends.numel() - 1, f'data/{key}')}: has {rows} rows but meta/episode_ends "
                    f"ends at {int(ends[-1])} (truncated or mismatched arrays)"
                )
        self.starts, self.ends = starts.tolist(), ends.tolist()

    @property
    def metadata(self) -> dict:
        return {
            **super().metadata,
            "control": "absolute",  # Diffusion Policy's zarr datasets (PushT, robomimic abs) use targets
            "has_rewards": False,
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

    def read_episode(self, episode: int) -> TensorDict:
        actions = self._read(episode, self.action_key).float()
        steps = actions.shape[0]
        actions = check_finite(actions.reshape(steps, -1), self.path, episode, f"data/{self.action_key}")
        columns = [
            check_finite(self._read(episode, k).float().reshape(steps, -1), self.path, episode, f"data/{k}")
            for k in self.state_keys
        ]
        state = torch.cat(columns, dim=-1) if columns else torch.zeros(steps, 0)
        observation: torch.Tensor | dict = state
        if self.image_key is not None:
            key = f"data/{self.image_key}"
            rgb = to_uint8_image(
                self._read(episode, self.image_key), self.path, episode, key, channels_last=True
            )
            observation = {"state": state, "rgb": rgb}
        return assemble_episode(episode, observation, actions)
