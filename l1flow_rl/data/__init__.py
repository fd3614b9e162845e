"""Demonstrations into TorchRL replay buffers.

    from l1flow_rl.data import load_episodes, make_chunk_buffer, fit_normalizers
    eps = load_episodes(path)                       # ManiSkill .h5, robomimic .hdf5, DP .zarr, LeRobot dir
    rb = make_chunk_buffer(eps, obs_horizon=2, pred_horizon=16, batch_size=64, seed=0)
    batch = rb.sample()                             # "observation" [64, 2, ...], "action_chunk" [64, 16, A]
    fit_normalizers(actor, eps)                     # limits (or gaussian) statistics into the actor

Demonstrations are made by the experts in :mod:`l1flow_rl.experts` (``l1flow-rl demos``).
"""

from l1flow_rl.data.buffer import make_chunk_buffer
from l1flow_rl.data.chunks import ChunkLayout, ChunkStorage, ChunkWindowSampler
from l1flow_rl.data.episodes import EpisodeDataError
from l1flow_rl.data.loading import episodes_metadata, load_episodes, open_episode_file
from l1flow_rl.data.normalization import fit_normalizers

__all__ = [
    "ChunkLayout",
    "ChunkStorage",
    "ChunkWindowSampler",
    "EpisodeDataError",
    "episodes_metadata",
    "fit_normalizers",
    "load_episodes",
    "make_chunk_buffer",
    "open_episode_file",
]
