"""A trained policy as a folder that needs neither this library's hydra config nor its training code.

The folder, in the shape LeRobot's users share policies in::

    config.json               what to build: the policy, network and encoder settings (sampler,
                              horizons; unet or mlp), the observation entries and action with shapes
                              and dtypes, the task it was trained on, the library version, where the
                              weights came from
    model.safetensors         the network and encoder weights (a checkpoint's EMA weights by default)
    normalizer.safetensors    the observation and action normalisers (scale, offset, mode per entry)
    train_config.json         the full config of the training run (provenance; not read to rebuild)
    policy.pt2                optional: the whole 2-NFE call as a ``torch.export`` program
                              (see :mod:`l1flow_rl.export.program`)

:func:`save_pretrained` writes it (``l1flow-rl export checkpoint=CKPT out=DIR`` from a checkpoint) and
:func:`load_pretrained` rebuilds the actor (``L1FlowActor.from_pretrained(DIR)``). Weights go through
safetensors, which stores tensors only, so loading runs no code from the file.

Example:
    >>> import tempfile, torch
    >>> from l1flow_rl import L1FlowActor
    >>> actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
    >>> folder = actor.save_pretrained(tempfile.mkdtemp() + "/policy")
    >>> again = L1FlowActor.from_pretrained(folder)
    >>> obs, noise = torch.randn(1, 2, 5), torch.randn(1, 16, 2)
    >>> bool((again.policy(obs, noise=noise) == actor.policy(obs, noise=noise)).all())
    True
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from l1flow_rl.export.folder import (
    CONFIG_FILE,
    FORMAT,
    FORMAT_VERSION,
    PretrainedFolderError,
    is_pretrained_folder,
    read_pretrained_config,
)
from l1flow_rl.modules.actor import L1FlowActor

__all__ = [
    "CONFIG_FILE",
    "FORMAT",
    "FORMAT_VERSION",
    "PretrainedFolderError",
    "is_pretrained_folder",
    "load_pretrained",
    "load_pretrained_for_eval",
    "read_pretrained_config",
    "save_pretrained",
]


def save_pretrained(actor: L1FlowActor, path: str | os.PathLike, **settings: Any) -> Path:
    """Write ``actor`` as a pretrained folder at ``path``; ``settings`` (``policy``, ``encoder``, ``task``,
    ``train_config``, ``source``, ``program``, ``onnx``) as
    :func:`~l1flow_rl.export.folder.write_folder`. Only an :class:`~l1flow_rl.L1FlowActor` is taken."""
    if not isinstance(actor, L1FlowActor):
        raise TypeError(
            f"save_pretrained takes an L1FlowActor, got {type(actor).__name__}; a best-of-N actor selects "
            "with critics that the folder does not hold: save its .actor"
        )
    return actor.save_pretrained(path, **settings)


def load_pretrained(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> L1FlowActor:
    """The actor a pretrained folder describes, with its weights and normalisers, in eval mode."""
    return L1FlowActor.from_pretrained(path, map_location)


def load_pretrained_for_eval(
    path: str | os.PathLike, map_location: str | torch.device = "cpu"
) -> tuple[L1FlowActor, DictConfig]:
    """(actor, a config with the ``task``, ``policy`` and ``network`` it was trained with) for
    ``l1flow-rl eval``."""
    config = read_pretrained_config(path)
    if not isinstance(config.get("task"), dict):
        raise PretrainedFolderError(
            f"{Path(path) / CONFIG_FILE}: records no task, so l1flow-rl eval cannot tell where to run it; "
            "export it from a training checkpoint (l1flow-rl export checkpoint=CKPT out=DIR)"
        )
    actor = load_pretrained(path, map_location)
    return actor, OmegaConf.create(
        {"task": config["task"], "policy": config["policy"], "network": config["network"]}
    )
