"""ManiSkill trajectory files: ``NAME.h5`` (``traj_<id>`` groups) plus ``NAME.json`` (env and episode info).

State files store ``obs`` as one flat array [T+1, D]; rgb files store the observation dict, which is
flattened the way ManiSkill's ``FlattenRGBDObservationWrapper`` does (``agent`` then ``extra`` leaves
as ``"state"``, the camera as channels-first ``"rgb"``), so offline data matches the live env.
Rewards: ``("next", "reward")`` is the recorded reward (the replay's ``--reward-mode``, e.g.
``normalized_dense``), or the sparse reward where none was recorded (then the metadata says
``has_rewards=False``, and RL refuses the file unless told to use ``("next", "sparse_reward")``);
``("next", "sparse_reward")`` is ManiSkill's sparse reward, success - fail, rebuilt from the per-step
flags. The T+1st observation ManiSkill records is the final observation, ``("next", "observation")``
at the last step.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import torch
from tensordict import TensorDict

from l1flow_rl.data import episodes
from l1flow_rl.data.episodes import EpisodeDataError, where
from l1flow_rl.data.formats.base import EpisodeFile, open_h5
from l1flow_rl.data.metadata import control_of
from l1flow_rl.envs.maniskill.obs import flatten_maniskill_obs

__all__ = ["ManiSkillFile"]


class ManiSkillFile(EpisodeFile):
    """Reader for a ManiSkill ``.h5`` + ``.json`` pair.

    Args:
        path: the ``.h5`` file; its ``.json`` must sit beside it.
        control_mode: when given, every episode must have been recorded in it.
        camera: which camera to use when the file has several (rgb files).
    """

    format_name = "maniskill"

    def __init__(self, path: Path, *, control_mode: str | None = None, camera: str | None = None) -> None:
        super().__init__(path)
        self.camera = camera
        json_path = path.with_suffix(".json")
        if not json_path.is_file():
            raise EpisodeDataError(
                f"{path}: a ManiSkill trajectory needs its metadata file {json_path}, which is missing"
            )
        try:
            meta = json.loads(json_path.read_text())
            self.env_info = meta["env_info"]
            self.episodes = meta["episodes"]
        except (json.JSONDecodeError, KeyError, TypeError) as err:
            raise EpisodeDataError(
                f"{json_path}: not a ManiSkill trajectory metadata file (truncated or not JSON with "
                f"'env_info' and 'episodes'): {err!r}"
            ) from err
        env_kwargs = self.env_info.get("env_kwargs", {})
        self.control_mode = env_kwargs.get("control_mode")
        self.obs_mode = env_kwargs.get("obs_mode")
        for ep in self.episodes:
            mode = ep.get("control_mode", self.control_mode)
            if control_mode is not None and mode != control_mode:
                raise EpisodeDataError(
                    f"{where(json_path, ep.get('episode_id'), 'control_mode')}: recorded in {mode!r}, but "
                    f"{control_mode!r} was requested; replay the demos into it with ManiSkill's replay tool "
                    f"(-c {control_mode}) or ask for {mode!r}"
                )
        self.h5 = open_h5(path)
        for ep in self.episodes:
            name = f"traj_{ep['episode_id']}"
            if name not in self.h5:
                raise EpisodeDataError(
                    f"{where(path, ep['episode_id'], name)}: listed in {json_path.name} but missing from "
                    "the file (truncated or mismatched pair)"
                )

    @property
    def metadata(self) -> dict:
        ids = self.episode_ids()
        return {
            "format": self.format_name,
            "source": str(self.path),
            "env_id": self.env_info.get("env_id"),
            "control_mode": self.control_mode,
            "control": control_of(self.control_mode),
            "has_rewards": all("rewards" in self.h5[f"traj_{e}"] for e in ids),
            "has_final_observation": all(self._obs_rows(e) == self.episode_length(e) + 1 for e in ids),
            "obs_mode": self.obs_mode,
        }

    def _obs_rows(self, episode: int) -> int:
        node = self._dataset(episode, "obs")
        while isinstance(node, h5py.Group):  # rgb files: the first leaf of agent/ tells the row count
            children = [node[k] for k in ("agent", "extra", *node.keys()) if k in node]
            if not children:
                return -1
            node = children[0]
        return node.shape[0]

    def episode_ids(self) -> list[int]:
        return [int(ep["episode_id"]) for ep in self.episodes]

    def episode_length(self, episode: int) -> int:
        return self._dataset(episode, "actions").shape[0]

    def episode_labels(self) -> dict[int, str] | None:
        """Each episode's ``quality`` entry in the ``.json``; None when no episode has one."""
        labels = {int(ep["episode_id"]): ep.get("quality") for ep in self.episodes}
        if all(v is None for v in labels.values()):
            return None
        missing = [e for e, v in labels.items() if v is None]
        if missing:
            raise EpisodeDataError(
                f"{where(self.path.with_suffix('.json'), missing[0], 'quality')}: missing, while other "
                f"episodes carry a quality label ({len(missing)} episodes lack one)"
            )
        return {e: str(v) for e, v in labels.items()}

    def _dataset(self, episode: int, key: str):
        group = self.h5[f"traj_{episode}"]
        if key not in group:
            raise EpisodeDataError(f"{where(self.path, episode, key)}: missing (has {sorted(group)})")
        return group[key]

    def _read(self, episode: int, key: str) -> torch.Tensor:
        return episodes.as_tensor(
            self._dataset(episode, key)[()], self.path, episode, f"traj_{episode}/{key}"
        )

    def _observation(self, episode: int, steps: int):
        node = self._dataset(episode, "obs")
        key = f"traj_{episode}/obs"
        if isinstance(node, h5py.Dataset):
            full = episodes.as_tensor(node[()], self.path, episode, key)
            obs = episodes.check_steps(full, steps, self.path, episode, key, extra=1)
            final = full[steps] if full.shape[0] > steps else None
            episodes.check_finite(full.float(), self.path, episode, key)
            return obs.float(), None if final is None else final.float()
        wanted = {g: node[g] for g in ("agent", "extra", "sensor_data") if g in node}
        raw = _read_group(wanted, self.path, episode, key)
        try:
            flat = flatten_maniskill_obs(raw, camera=self.camera)
        except (KeyError, TypeError, ValueError) as err:
            raise EpisodeDataError(f"{where(self.path, episode, key)}: {err}") from err
        full_state = flat["state"]
        state = episodes.check_steps(full_state, steps, self.path, episode, f"{key}/agent+extra", extra=1)
        episodes.check_finite(full_state, self.path, episode, f"{key}/agent+extra")
        has_final = full_state.shape[0] > steps
        if "rgb" not in flat:
            return state, full_state[steps] if has_final else None
        episodes.check_steps(flat["rgb"], steps, self.path, episode, f"{key}/sensor_data", extra=1)
        if (flat["rgb"].shape[0] > steps) != has_final:
            raise EpisodeDataError(
                f"{where(self.path, episode, key)}: the camera has {flat['rgb'].shape[0]} frames but the "
                f"state {full_state.shape[0]} rows"
            )
        rgb = episodes.to_uint8_image(flat["rgb"], self.path, episode, key, channels_last=False)
        obs = {"state": state, "rgb": rgb[:steps]}
        return obs, {"state": full_state[steps], "rgb": rgb[steps]} if has_final else None

    def read_episode(self, episode: int) -> TensorDict:
        actions = self._read(episode, "actions")
        steps = actions.shape[0]
        if actions.dim() != 2 or steps == 0:
            raise EpisodeDataError(
                f"{where(self.path, episode, f'traj_{episode}/actions')}: expected [T >= 1, A], got "
                f"{tuple(actions.shape)}"
            )
        episodes.check_finite(actions, self.path, episode, f"traj_{episode}/actions")
        observation, final = self._observation(episode, steps)
        group = self.h5[f"traj_{episode}"]
        flags = {}
        for name in ("success", "fail", "terminated"):
            if name in group:
                flags[name] = episodes.check_steps(
                    self._read(episode, name).bool(), steps, self.path, episode, name
                )
        sparse = torch.zeros(steps)
        if "success" in flags:
            sparse = flags["success"].float() - (flags["fail"].float() if "fail" in flags else 0.0)
        reward = None
        if "rewards" in group:
            reward = episodes.check_steps(
                self._read(episode, "rewards"), steps, self.path, episode, "rewards"
            )
            episodes.check_finite(reward, self.path, episode, f"traj_{episode}/rewards")
        extra = {"sparse_reward": sparse}
        if "success" in flags:
            extra["success"] = flags["success"]
        return episodes.assemble_episode(
            episode,
            observation,
            actions,
            reward=reward if reward is not None else sparse,
            terminated=bool(flags["terminated"][-1]) if "terminated" in flags else False,
            final_observation=final,
            next_extra=extra,
        )

    def close(self) -> None:
        self.h5.close()


def _read_group(group, source, episode, key) -> dict:
    out = {}
    for name, node in group.items():
        if isinstance(node, h5py.Group):
            out[name] = _read_group(node, source, episode, f"{key}/{name}")
        elif name in ("depth", "segmentation", "seg"):
            continue  # only rgb is used; skip decompressing the other image streams
        else:
            out[name] = episodes.as_tensor(node[()], source, episode, f"{key}/{name}").numpy()
    return out
