"""The training data of a run: the task's demonstrations (made by its expert, or a user's file named
by ``data.path``), loaded as episodes, cut into chunk windows by a seeded replay buffer."""

from __future__ import annotations

from pathlib import Path

import torch.distributed as dist
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.data import TensorDictReplayBuffer

from l1flow_rl.config.data import PADDING_RULES, shifted_replay_problems
from l1flow_rl.config.validate import ConfigValidationError
from l1flow_rl.data import (
    EpisodeDataError,
    action_pad_for,
    episodes_metadata,
    load_episodes,
    make_chunk_buffer,
)
from l1flow_rl.data.loading import open_episode_file
from l1flow_rl.envs import get_simulator
from l1flow_rl.evaluation.plan import task_from
from l1flow_rl.experts import ensure_demos
from l1flow_rl.experts.options import demo_options

__all__ = ["chunk_padding", "load_task_episodes", "make_train_buffer", "resolve_dataset"]


def resolve_dataset(cfg: DictConfig, rank: int = 0, world: int = 1) -> Path:
    """``data.path`` when given, else the expert's cached (or newly made) demonstrations. Only rank 0
    makes demonstrations; the others receive the path."""
    if rank == 0:
        task = OmegaConf.to_object(cfg.task)
        problems = shifted_replay_problems(cfg)  # again: a fine-tune adopts its start's data.path
        if problems:
            raise ConfigValidationError(problems[0])
        if cfg.data.path:
            dataset = Path(cfg.data.path)
            prepare = get_simulator(task.simulator).prepare_dataset
            if prepare is not None:  # e.g. robosuite: observations regenerated from stored states
                dataset = prepare(task, dataset, Path(cfg.data_dir))
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
    """The dataset's episodes, checked against the task's control mode where the file records one
    (before anything is read). Image datasets stay memory-mapped on disk next to the
    demonstrations instead of in RAM."""
    # the entries of the task's observation (robosuite: state_keys, cameras), where its simulator says
    select = get_simulator(cfg.task.simulator).reader_options
    options = dict(select(task_from(cfg.task))) if select is not None else {}  # a checkpoint's plain node too
    # Any format, any simulator: the recorded mode comes from the reader's metadata, not from a
    # reader option that only some formats take.
    with open_episode_file(dataset, **options) as reader:
        recorded = reader.metadata.get("control_mode")
    if recorded is not None and recorded != cfg.task.control_mode:
        raise EpisodeDataError(
            f"{dataset}: recorded with control_mode {recorded!r}, but task.control_mode is "
            f"{cfg.task.control_mode!r}; use demonstrations recorded in {cfg.task.control_mode!r} or set "
            f"task.control_mode={recorded}"
        )
    memmap_dir = dataset.with_suffix(".memmap") if cfg.task.obs_mode != "state" else None
    labels = list(cfg.data.labels) if cfg.data.get("labels") is not None else None
    return load_episodes(dataset, memmap_dir=memmap_dir, labels=labels, **options)


def chunk_padding(cfg: DictConfig, episodes: TensorDictBase) -> dict:
    """How the run's chunks are padded past an episode's end (``make_chunk_buffer`` arguments).

    The padded actions follow the control the data record (zero arm motion for delta control, the
    last action for absolute), checked against ``task.control``; data that record none take the task's.
    The extent follows ``data.padding``: ``maniskill`` pads up to H - To steps after the end (every
    step is a window's current step), ``diffusion_policy`` at most K - 1 (K = ``policy.action_steps``;
    the To - 1 steps before the start are padded under both).
    """
    meta = episodes_metadata(episodes)
    task_control = cfg.task.control
    if meta.control is not None and meta.control != task_control:
        raise EpisodeDataError(
            f"{meta.describe()}: recorded with {meta.control} control (control_mode {meta.control_mode!r}), "
            f"but task.control is {task_control!r}; chunks would be padded for the wrong control. Use "
            f"demonstrations recorded with {task_control} control or set task.control={meta.control}"
        )
    pcfg = cfg.policy
    padding = cfg.data.padding
    if padding == "maniskill":
        max_pad_after = None
    elif padding == "diffusion_policy":
        max_pad_after = int(pcfg.action_steps) - 1
        most = int(pcfg.pred_horizon) - int(pcfg.obs_horizon)
        if not 0 <= max_pad_after <= most:
            raise ValueError(
                f"data.padding=diffusion_policy pads policy.action_steps - 1 = {max_pad_after} steps after "
                f"an episode's end, which must lie in [0, policy.pred_horizon - policy.obs_horizon = {most}]"
            )
    else:
        raise ValueError(f"data.padding must be one of {list(PADDING_RULES)}, got {padding!r}")
    return {"action_pad": action_pad_for(meta.control or task_control), "max_pad_after": max_pad_after}


def make_train_buffer(cfg: DictConfig, episodes: TensorDictBase, seed: int) -> TensorDictReplayBuffer:
    """The run's seeded chunk buffer, padded as :func:`chunk_padding` decides."""
    pcfg, tcfg = cfg.policy, cfg.train
    return make_chunk_buffer(
        episodes,
        obs_horizon=pcfg.obs_horizon,
        pred_horizon=pcfg.pred_horizon,
        batch_size=tcfg.batch_size,
        seed=seed,
        prefetch=tcfg.prefetch or None,
        **chunk_padding(cfg, episodes),
    )
