"""Demonstrations into TorchRL replay buffers.

    from l1flow_rl.data import load_episodes, make_chunk_buffer, fit_normalizers
    eps = load_episodes(path)                       # ManiSkill .h5, robomimic .hdf5, DP .zarr, LeRobot dir
    rb = make_chunk_buffer(eps, obs_horizon=2, pred_horizon=16, batch_size=64, seed=0)
    batch = rb.sample()                             # "observation" [64, 2, ...], "action_chunk" [64, 16, A]
    fit_normalizers(actor, eps)                     # limits (or gaussian) statistics into the actor
    episodes_metadata(eps).control                  # 'delta' | 'absolute' | None, kept through eps[...]

    # RL: chunk returns, next observations and validity for a chunked critic; online data
    rb = make_chunk_buffer(eps, rl_horizon=5, gamma=0.99, capacity=100_000)   # writable
    rb.extend(collector_batch)                      # complete episodes stored, unfinished ones held

Demonstrations are made by the experts in :mod:`l1flow_rl.experts` (``l1flow-rl demos``).
"""

from l1flow_rl.data.buffer import action_pad_for, make_chunk_buffer
from l1flow_rl.data.chunks import ChunkLayout, ChunkStorage, ChunkWindowSampler
from l1flow_rl.data.episodes import EpisodeDataError
from l1flow_rl.data.loading import load_episodes, open_episode_file
from l1flow_rl.data.metadata import EpisodeMetadata, attach_metadata, episodes_metadata
from l1flow_rl.data.normalization import fit_normalizers
from l1flow_rl.data.online import CollectorEpisodes, EpisodeWriter

__all__ = [
    "ChunkLayout",
    "ChunkStorage",
    "ChunkWindowSampler",
    "CollectorEpisodes",
    "EpisodeDataError",
    "EpisodeMetadata",
    "EpisodeWriter",
    "action_pad_for",
    "attach_metadata",
    "episodes_metadata",
    "fit_normalizers",
    "load_episodes",
    "make_chunk_buffer",
    "open_episode_file",
]
