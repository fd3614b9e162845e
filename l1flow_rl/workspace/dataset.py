"""The training data of a run: the task's demonstrations (made by its expert, or a user's file named
by ``data.path``), loaded as episodes, cut into chunk windows by a seeded replay buffer."""

from __future__ import annotations

from pathlib import Path

import torch.distributed as dist
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.data import TensorDictReplayBuffer

__all__ = ["load_task_episodes", "make_train_buffer", "resolve_dataset"]


def resolve_dataset(cfg: DictConfig, rank: int = 0, world: int = 1) -> Path:
    """``data.path`` when given, else the expert's cached (or newly made) demonstrations. Only rank 0
    makes demonstrations; the others receive the path."""
    from l1flow_rl.experts import ensure_demos
    from l1flow_rl.experts.cli import demo_options

    if rank == 0:
        task = OmegaConf.to_object(cfg.task)
        if cfg.data.path:
            dataset = Path(cfg.data.path)
        else:
            dataset = ensure_demos(
                task, cfg.demos.num, cfg.data_dir, seed=cfg.demos.seed, **demo_options(cfg, task)
            )
        paths = [str(dataset)]
    else:
        paths = [""]
    if world > 1:
        dist.broadcast_object_list(paths, src=0)
    return Path(paths[0])


def load_task_episodes(cfg: DictConfig, dataset: Path) -> TensorDictBase:
    """The dataset's episodes, checked against the task's control mode. Image datasets stay
    memory-mapped on disk next to the demonstrations instead of in RAM."""
    from l1flow_rl.data import load_episodes

    memmap_dir = dataset.with_suffix(".memmap") if cfg.task.obs_mode != "state" else None
    return load_episodes(dataset, control_mode=cfg.task.control_mode, memmap_dir=memmap_dir)


def make_train_buffer(cfg: DictConfig, episodes: TensorDictBase, seed: int) -> TensorDictReplayBuffer:
    from l1flow_rl.data import make_chunk_buffer

    pcfg, tcfg = cfg.policy, cfg.train
    return make_chunk_buffer(
        episodes,
        obs_horizon=pcfg.obs_horizon,
        pred_horizon=pcfg.pred_horizon,
        batch_size=tcfg.batch_size,
        seed=seed,
        action_pad="delta" if cfg.task.control == "delta" else "repeat",
        prefetch=tcfg.prefetch or None,
    )
