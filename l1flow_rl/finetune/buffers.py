"""The fine-tuning run's replay data: demonstrations and online episodes as chunk windows with RL targets.

* By default (RLPD, QC) the demonstrations and the online episodes sit in two buffers, and every
  batch takes exactly ``online.offline_fraction`` of its windows from the demonstrations (TorchRL's
  ``OfflineToOnlineReplayBuffer``); with ``offline_fraction=0`` the demonstrations are only the
  offline phase's data (DSRL).
* ``online.seed_with_offline`` (FQL's alternative): one writable buffer that the demonstrations
  seed and online episodes extend; batches are drawn uniformly over everything stored.
"""

from __future__ import annotations

import io
import pickle
import shutil
from pathlib import Path
from typing import Any

from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.data import OfflineToOnlineReplayBuffer, TensorDictReplayBuffer

from l1flow_rl.config.finetune import REWARD_KEYS, round_frames
from l1flow_rl.data import EpisodeDataError, make_chunk_buffer
from l1flow_rl.data.episodes import episode_bounds
from l1flow_rl.data.online import CORE_KEYS
from l1flow_rl.errors import CheckpointReadError
from l1flow_rl.workspace.checkpoint import get_buffer_rng, set_buffer_rng
from l1flow_rl.workspace.dataset import chunk_padding

__all__ = ["ChunkOfflineToOnlineBuffer", "RLBuffers"]


class ChunkOfflineToOnlineBuffer(OfflineToOnlineReplayBuffer):
    """TorchRL's exact per-batch offline/online split, over two chunk-window buffers.

    ``OfflineToOnlineReplayBuffer`` wraps a bare online storage in a uniform row sampler, which cannot
    cut chunk windows; here the online buffer (its own window sampler and episode writer) is handed in
    whole and the parent's ``sample``/``anneal``/``extend`` work unchanged.
    """

    def __init__(
        self,
        offline: TensorDictReplayBuffer,
        online: TensorDictReplayBuffer,
        *,
        offline_fraction: float,
        batch_size: int,
    ) -> None:
        super().__init__(offline, online_capacity=1, offline_fraction=offline_fraction, batch_size=batch_size)
        self._online_buffer = online


def n_episodes(episodes: TensorDictBase, ended_terminated: bool = False) -> int:
    """How many episodes ``episodes`` holds (rows grouped by ``"episode"``); with
    ``ended_terminated``, only those whose last step is terminated (success)."""
    last = episode_bounds(episodes.get("episode"))[1].unique() - 1  # each episode's last row
    if ended_terminated:
        terminated = episodes.get(("next", "terminated")).reshape(episodes.shape[0], -1)[:, 0].bool()
        return int(terminated[last].sum())
    return int(last.numel())


def _check_sparse_source(episodes: TensorDictBase, cfg: DictConfig) -> None:
    """``finetune.reward=sparse`` reads success from the terminal steps: demonstrations recorded
    with terminations off (no episode terminates) would give the critic no reward at all."""
    terminated = episodes.get(("next", "terminated"), None)
    if terminated is None or not bool(terminated.any()):
        raise ValueError(
            f"finetune.reward=sparse: no demonstration episode of task {cfg.task.name!r} ends in a "
            "terminal state (('next', 'terminated') is never true), so the sparse reward (1 at the "
            "terminal step) would be 0 everywhere; record demonstrations that end at success, or use "
            "finetune.reward=recorded"
        )


class RLBuffers:
    """Demonstration and online chunk buffers of one run, with RL targets for the critic.

    Args:
        cfg: the composed run config (``policy``, ``task``, ``finetune``, ``online`` groups).
        episodes: the demonstrations (with rewards and next observations).
        rl_horizon: h, the critic's executed chunk length.
        seed: seeds the buffers' generators.
        online_keys: per-step entries the online buffer keeps beside the core ones (the
            algorithm's, e.g. DSRL's noise).
        online_anchor_key: online windows start only where this stored entry is 1 (DSRL's chunk
            starts); None: at every step.
        successful_episodes_only: windows only in episodes that ended in a terminal state (success
            here; filtered behaviour cloning), in the demonstrations (a mixed-quality set's failures
            drop out) and online. Until an online episode qualifies, batches are the demonstrations'
            alone, counted in :attr:`demo_only_batches`.
        return_discount: the discount of the rewards within a chunk's return (None:
            ``finetune.gamma``, per env step; 1.0 where gamma is per chunk decision, as DSRL's).
    """

    def __init__(
        self,
        cfg: DictConfig,
        episodes: TensorDictBase,
        rl_horizon: int,
        seed: int,
        online_keys: tuple[str, ...] = (),
        online_anchor_key: str | None = None,
        successful_episodes_only: bool = False,
        return_discount: float | None = None,
    ) -> None:
        ocfg = cfg.online
        if not 0.0 <= ocfg.offline_fraction < 1.0:
            raise ValueError(f"online.offline_fraction must lie in [0, 1), got {ocfg.offline_fraction}")
        self.mixing = (
            "seed" if ocfg.seed_with_offline else ("balanced" if ocfg.offline_fraction > 0 else "online")
        )
        reward = str(cfg.finetune.reward)
        if reward not in REWARD_KEYS:
            raise ValueError(f"finetune.reward={reward!r}; expected one of {tuple(REWARD_KEYS)}")
        if reward == "sparse":
            _check_sparse_source(episodes, cfg)
        n_demo = int(episodes.shape[0])
        # room for every online step plus the unfinished episodes a round end flushes
        online_capacity = int(ocfg.capacity) or int(ocfg.steps) + round_frames(cfg)
        common = dict(
            obs_horizon=cfg.policy.obs_horizon,
            pred_horizon=cfg.policy.pred_horizon,
            batch_size=cfg.finetune.batch_size,
            **chunk_padding(cfg, episodes),  # the BC run's rule: recorded control, data.padding
            rl_horizon=rl_horizon,
            gamma=cfg.finetune.gamma if return_discount is None else float(return_discount),
            reward_key=REWARD_KEYS[reward],
            keys=CORE_KEYS,  # demonstrations and online episodes share one set of entries
            terminated_episodes_only=successful_episodes_only,
        )
        online = (*CORE_KEYS, *online_keys)
        if online_anchor_key is not None and online_anchor_key not in online:
            raise ValueError(f"online_anchor_key={online_anchor_key!r} is not among the stored {online}")

        def online_buffer():  # reads ``common`` when called: the balanced branch drops its batch size
            return make_chunk_buffer(
                None,
                seed=seed + 1,
                capacity=max(online_capacity, 1),
                **{
                    **common,
                    "keys": online,
                    "anchor_key": online_anchor_key,
                },
            )

        if self.mixing == "seed":
            if online_keys:
                raise ValueError(
                    f"online.seed_with_offline: the demonstrations lack the entries {list(online_keys)} "
                    "this algorithm stores per step; keep them in separate buffers"
                )
            self.offline = make_chunk_buffer(
                episodes, seed=seed, capacity=n_demo + (online_capacity if ocfg.steps > 0 else 0), **common
            )
            self.online = self.offline
            self.mixed: Any = self.offline
        elif self.mixing == "balanced":
            # the parent asks each buffer for its share of a batch; no default size avoids TorchRL's
            # "conflicting batch sizes" warning on every draw
            common["batch_size"] = None
            self.offline = make_chunk_buffer(episodes, seed=seed, capacity=n_demo, **common)
            self.online = online_buffer()
            self.mixed = ChunkOfflineToOnlineBuffer(
                self.offline,
                self.online,
                offline_fraction=ocfg.offline_fraction,
                batch_size=cfg.finetune.batch_size,
            )
        else:  # online data only
            self.offline = make_chunk_buffer(episodes, seed=seed, capacity=n_demo, **common)
            self.online = online_buffer()
            self.mixed = self.online
        self.batch_size = int(cfg.finetune.batch_size)
        #: demonstration episodes whose windows the batches draw from, of all given
        self.demo_episodes = {"kept": n_episodes(episodes), "given": n_episodes(episodes)}
        if successful_episodes_only:
            self.demo_episodes["kept"] = n_episodes(episodes, ended_terminated=True)
            if self.demo_episodes["kept"] == 0:  # before the start's validation, not at the first batch
                raise EpisodeDataError(
                    f"finetune.algorithm={cfg.finetune.algorithm}: none of the {self.demo_episodes['given']} "
                    f"demonstration episodes of task {cfg.task.name!r} ends in success (a terminated last "
                    "step), and this algorithm trains only on successful episodes"
                )
        self.online_steps_stored = 0
        self.demo_only_batches = 0

    def sample_offline(self) -> TensorDictBase:
        return self.offline.sample(self.batch_size)

    def sample_online(self) -> TensorDictBase:
        if self.mixed is not self.online and self.online_windows() == 0:
            self.demo_only_batches += 1  # no qualifying online episode yet: logged, not hidden
            return self.offline.sample(self.batch_size)
        return self.mixed.sample()

    def online_windows(self) -> int:
        """Windows the online episodes give now (0 before any qualifies)."""
        return self.online.sampler.window_count(self.online.storage)

    def add_collected(self, batch: TensorDictBase) -> int:
        """Store a collector round: finished episodes, then (round end) the unfinished ones as
        truncated, so that no episode spans two rounds. Returns the steps stored."""
        written = self.online.extend(batch)
        flushed = self.online.writer.flush()
        stored = int((written >= 0).sum()) + int(flushed)
        self.online_steps_stored += stored
        return stored

    # -- checkpointing ------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {
            "offline_rng": get_buffer_rng(self.offline),
            "online_rng": get_buffer_rng(self.online),
            "online_steps_stored": self.online_steps_stored,
            "demo_only_batches": self.demo_only_batches,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        set_buffer_rng(self.offline, state["offline_rng"])
        set_buffer_rng(self.online, state["online_rng"])
        self.online_steps_stored = int(state["online_steps_stored"])
        self.demo_only_batches = int(state.get("demo_only_batches", 0))  # absent before filtered BC

    def dump_online(self, directory: Path) -> None:
        """The online buffer (storage, writer, generator) under ``directory``, written atomically."""
        directory.parent.mkdir(parents=True, exist_ok=True)  # the run's first checkpoint may be this one
        tmp = directory.parent / f".{directory.name}.partial"
        shutil.rmtree(tmp, ignore_errors=True)
        self.online.dumps(tmp)
        shutil.rmtree(directory, ignore_errors=True)
        tmp.rename(directory)

    def load_online(self, directory: Path) -> None:
        if not directory.is_dir():
            raise FileNotFoundError(
                f"the checkpoint names the online buffer {str(directory)!r}, which does not exist"
            )
        _refuse_unsafe_prefetch_state(directory / "prefetch.pkl")
        self.online.loads(directory)


class _BuiltinsOnly(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        raise pickle.UnpicklingError(f"{module}.{name}")


def _refuse_unsafe_prefetch_state(path: Path) -> None:
    """TorchRL's ``ReplayBuffer.loads`` unpickles ``prefetch.pkl`` with plain ``pickle.load``, which
    runs whatever code the file names. Ours (no prefetch) holds builtins only; read it first with
    an unpickler that resolves no class, so a planted or foreign file is refused before TorchRL
    loads it."""
    if not path.is_file():
        return  # TorchRL reads no prefetch state then
    try:
        _BuiltinsOnly(io.BytesIO(path.read_bytes())).load()
    except pickle.UnpicklingError as err:
        raise CheckpointReadError(
            f"online buffer file {str(path)!r} cannot be read safely (it names {err}): an l1flow-rl "
            "run writes builtins only there; resume only from run directories you trust"
        ) from None
    except Exception as err:  # torn or not a pickle at all
        raise CheckpointReadError(f"online buffer file {str(path)!r} is not readable: {err}") from None
