"""Checkpoints: atomic writes, safe loads (``weights_only=True``) and config checks.

A checkpoint is a plain dict of tensors and builtins: model, EMA, optimiser, scheduler, step, the
composed config, data shapes and RNG states. Nothing in it needs arbitrary unpickling.
"""

from __future__ import annotations

import fnmatch
import os
import pickle
import random
import re
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from l1flow_rl.config.network import NetworkConfig, upgrade_saved_config
from l1flow_rl.errors import CheckpointMismatchError, CheckpointReadError
from l1flow_rl.finetune.registry import get_algorithm
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.utils.state_dict import load_state_into
from l1flow_rl.workspace.build import build_actor

__all__ = [
    "RESUME_MAY_CHANGE",
    "CheckpointMismatchError",
    "CheckpointNotFoundError",
    "CheckpointReadError",
    "ResumeMismatchError",
    "check_compatible",
    "check_resumable",
    "config_differences",
    "first_non_finite",
    "flatten_config",
    "get_buffer_rng",
    "get_rng_state",
    "load_actor",
    "load_checkpoint",
    "save_checkpoint",
    "set_buffer_rng",
    "set_rng_state",
]

# Config fields that change the network or its data; a checkpoint only fits a config that agrees on all.
_IDENTITY_FIELDS = (
    "task.env_id",
    "task.obs_mode",
    "task.control_mode",
    "policy.loss",
    "policy.obs_horizon",
    "policy.pred_horizon",
    "policy.action_steps",
    *(f"network.{f}" for f in NetworkConfig.__dataclass_fields__),
)
#: identity fields added after checkpoints were made: what a checkpoint without one was built with
_IDENTITY_DEFAULTS = {"network.timestep_scale": 1.0}


#: Config fields a resumed run of any job may set differently from the run it continues (dotted,
#: ``*`` matches any rest): evaluation, the logger, where things run, and the evaluation-only env
#: options. Each job adds its own (its cadences, say) with ``check_resumable(..., may_change=...)``.
#: Every other field (the task and its data: ``task.*``, ``demos.*``, ``data.*``, ``seed``; the
#: schedule; the method and network: ``policy.*``) must match, or the resumed run would not be the
#: run it claims to continue.
RESUME_MAY_CHANGE: tuple[str, ...] = (
    "eval.*",
    "train.logger",
    "task.max_episode_steps",  # the evaluation horizon; the demonstrations are already made
    "task.env",  # simulator options of the evaluation env
    "task.env.*",
    "device",
    "data_dir",  # where the demonstrations cache lives, not which demonstrations
    "run_dir",
    "resume",
    "toy.*",  # the toy command's group: no training job reads it
)


class CheckpointNotFoundError(CheckpointReadError, FileNotFoundError):
    """No checkpoint where one was named."""


class ResumeMismatchError(CheckpointMismatchError):
    """``resume=true`` with a config that changes the data, the schedule or the method."""


def save_checkpoint(path: str | Path, state: Mapping[str, Any]) -> Path:
    """Write ``state`` to ``path`` atomically: a temporary file in the same folder, fsync, rename.

    A kill at any moment leaves either the previous file or the new one, never a torn one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(dict(state), f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)  # make the rename itself durable
    finally:
        os.close(dir_fd)
    return path


def load_checkpoint(
    path: str | Path, map_location: str | torch.device = "cpu", *, mmap: bool = False
) -> dict[str, Any]:
    """Load with ``weights_only=True``: tensors and builtins only, never arbitrary code. ``mmap``: map
    the tensors instead of reading them (a config check that reads only the recorded config).

    A missing, truncated or foreign file raises :class:`~l1flow_rl.errors.CheckpointReadError`
    naming the file. A file holding other Python objects is refused without torch's advice to
    retry with ``weights_only=False``, which would run whatever code the file carries.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "latest.pt"
    if not path.is_file():
        raise CheckpointNotFoundError(f"checkpoint {str(path)!r} does not exist")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except pickle.UnpicklingError as err:  # objects beyond tensors and builtins: not ours
        found = re.search(r"GLOBAL (\S+)", str(err))
        what = f" (it holds {found.group(1)})" if found else ""
        raise CheckpointReadError(
            f"checkpoint {str(path)!r} cannot be read safely{what}: it is not an l1flow-rl checkpoint, "
            "whose entries are tensors and builtins only"
        ) from None  # torch's message advises weights_only=False: never, for a file of unknown origin
    except Exception as err:  # torn, empty or not a torch file at all
        raise CheckpointReadError(
            f"checkpoint {str(path)!r} cannot be read safely: it is truncated or not a torch checkpoint "
            f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else 'no data'}); "
            "use another checkpoint, e.g. best.pt or the run's previous latest.pt"
        ) from err
    if not isinstance(state, dict):
        raise CheckpointReadError(f"checkpoint {str(path)!r} holds a {type(state).__name__}, not a dict")
    for key in ("model", "config"):
        if key not in state:
            raise CheckpointReadError(
                f"checkpoint {str(path)!r} has no {key!r} entry; is it an l1flow-rl checkpoint?"
            )
    for key in ("config", "run_config"):  # one from before the network group: its UNet as network
        if isinstance(state.get(key), dict):
            state[key] = upgrade_saved_config(state[key])
    return state


def first_non_finite(state: Mapping[str, Any], prefix: str = "") -> str | None:
    """The dotted name of the first floating-point tensor in ``state`` (nested mappings and lists)
    holding a NaN or an infinity, or None. One host read per device when all are finite.

    >>> nan = torch.tensor([1.0, float("nan")])
    >>> first_non_finite({"model": {"w": torch.ones(2)}, "optimizer": {"m": [nan]}})
    'optimizer.m.0'
    """
    found: list[tuple[str, torch.Tensor]] = []

    def walk(node: Any, name: str) -> None:
        if isinstance(node, torch.Tensor):
            if node.is_floating_point() and node.numel():
                found.append((name, node))
        elif isinstance(node, Mapping):
            for key, value in node.items():
                walk(value, f"{name}{key}.")
        elif isinstance(node, (list, tuple)):
            for i, value in enumerate(node):
                walk(value, f"{name}{i}.")

    walk(state, prefix)
    by_device: dict[torch.device, list[torch.Tensor]] = {}
    for _, tensor in found:
        by_device.setdefault(tensor.device, []).append(tensor.isfinite().all())
    if all(bool(torch.stack(flags).all()) for flags in by_device.values()):
        return None
    return next(name[:-1] for name, tensor in found if not bool(tensor.isfinite().all()))


def _select(cfg: Mapping[str, Any], dotted: str) -> Any:
    node: Any = cfg
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    return node


def check_compatible(
    saved_cfg: Mapping[str, Any], cfg: DictConfig | Mapping[str, Any], path: str = ""
) -> None:
    """Raise :class:`CheckpointMismatchError` listing every identity field that differs (a config
    from before the network group is read in the current layout first)."""
    current = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else cfg
    saved_cfg, current = upgrade_saved_config(dict(saved_cfg)), upgrade_saved_config(dict(current))

    def value(c: Mapping[str, Any], f: str) -> Any:
        found = _select(c, f)
        return _IDENTITY_DEFAULTS.get(f) if found is None else found

    diffs = [
        f"{f}: checkpoint has {value(saved_cfg, f)!r}, config asks for {value(current, f)!r}"
        for f in _IDENTITY_FIELDS
        if value(saved_cfg, f) != value(current, f)
    ]
    if diffs:
        raise CheckpointMismatchError(
            f"checkpoint {path!r} does not fit this config:\n  " + "\n  ".join(diffs)
        )


def flatten_config(node: Any, prefix: str = "") -> dict[str, Any]:
    """Dotted leaf paths of a nested mapping; lists are leaves; an empty mapping is a leaf.

    Example:
        >>> flatten_config({"train": {"steps": 10, "betas": [0.9, 0.99]}, "eval": {}})
        {'train.steps': 10, 'train.betas': [0.9, 0.99], 'eval': {}}
    """
    if isinstance(node, Mapping) and node:
        out: dict[str, Any] = {}
        for key, value in node.items():
            out.update(flatten_config(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: node}


def check_resumable(
    saved_cfg: Mapping[str, Any],
    cfg: DictConfig | Mapping[str, Any],
    path: str = "",
    may_change: tuple[str, ...] = (),
) -> None:
    """Raise :class:`ResumeMismatchError` naming every field that differs from the checkpoint's
    config, except those in :data:`RESUME_MAY_CHANGE` and the job's own ``may_change``. A field
    the checkpoint does not record (it predates the field) is not compared.

    Example:
        >>> saved = {"train": {"steps": 100, "log_every": 10}, "demos": {"num": 5}}
        >>> asked = {"train": {"steps": 100, "log_every": 50}, "demos": {"num": 5}}
        >>> check_resumable(saved, asked, may_change=("train.log_every",))  # the job allows it
        >>> try:
        ...     check_resumable(saved, {"train": {"steps": 200, "log_every": 10}, "demos": {"num": 5}})
        ... except ResumeMismatchError as err:
        ...     print(str(err).splitlines()[1])
          train.steps: checkpoint has 100, config asks for 200
    """
    allowed = (*RESUME_MAY_CHANGE, *may_change)
    diffs = config_differences(saved_cfg, cfg, allowed)
    if diffs:
        raise ResumeMismatchError(
            f"resume=true: checkpoint {path!r} was trained with another config:\n  "
            + "\n  ".join(diffs)
            + "\nOn resume only these may change: "
            + ", ".join(allowed)
            + ". To change the others, start a new run (drop resume=true)."
        )


def config_differences(
    saved_cfg: Mapping[str, Any],
    cfg: DictConfig | Mapping[str, Any],
    may_differ: tuple[str, ...] = (),
    saved_as: str = "checkpoint",
) -> list[str]:
    """One line per field of ``saved_cfg`` whose value ``cfg`` changes (``"key: <saved_as> has X,
    config asks for Y"``), leaving out the fields matching a ``may_differ`` pattern (``fnmatch``) and
    those ``saved_cfg`` does not record (it predates them). Every group is compared, ``network``
    included.

    Example:
        >>> config_differences({"network": {"down_dims": [16, 32]}}, {"network": {"down_dims": [32]}})
        ['network.down_dims: checkpoint has [16, 32], config asks for [32]']
    """
    current = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else cfg
    old, new = flatten_config(saved_cfg), flatten_config(current)
    return [
        f"{key}: {saved_as} has {old[key]!r}, config asks for {new.get(key)!r}"
        for key in old
        if old[key] != new.get(key) and not any(fnmatch.fnmatchcase(key, p) for p in may_differ)
    ]


def load_actor(
    path: str | Path, *, use_ema: bool = True, map_location: str | torch.device = "cpu"
) -> tuple[L1FlowActor, DictConfig]:
    """Rebuild the actor a checkpoint was trained with (EMA weights by default) and its config: an
    :class:`~l1flow_rl.L1FlowActor`, or for a fine-tuning run the acting module of its algorithm
    (its config's ``policy.finetune`` block, :mod:`l1flow_rl.finetune.registry`) around one."""
    state = load_checkpoint(path, map_location)
    cfg = OmegaConf.create(state["config"])
    shapes = {k: tuple(v) for k, v in state["obs_shapes"].items()}
    actor = build_actor(cfg.policy, shapes, int(state["action_dim"]), cfg.get("encoder"), cfg.get("network"))
    finetune = cfg.policy.get("finetune")
    if finetune:  # a fine-tuned policy: the algorithm's acting module around the flow
        actor = get_algorithm(finetune.algorithm).build(actor, finetune).actor
    weights = state["ema"] if use_ema and state.get("ema") is not None else state["model"]
    load_state_into(actor, weights, str(path))
    return actor.to(map_location).eval(), cfg


def get_rng_state() -> dict[str, Any]:
    """Every RNG the training loop draws from, as tensors and builtins (safe for weights_only)."""
    np_state = np.random.get_state()
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": {
            "keys": torch.from_numpy(np_state[1].astype(np.int64)),
            "pos": int(np_state[2]),
            "has_gauss": int(np_state[3]),
            "cached_gaussian": float(np_state[4]),
        },
        "python": [list(x) if isinstance(x, tuple) else x for x in random.getstate()],
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: Mapping[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state(
        ("MT19937", n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached_gaussian"])
    )
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def get_buffer_rng(buffer) -> torch.Tensor:
    """The state of a TorchRL replay buffer's generator (its sampler draws from it)."""
    # TorchRL exposes set_rng but no getter; its own state_dict reads the same attribute.
    return buffer._rng.get_state().clone()


def set_buffer_rng(buffer, state: torch.Tensor) -> None:
    generator = torch.Generator()
    generator.set_state(state)
    buffer.set_rng(generator)
