"""Loading a state_dict into a network with an error that says what does not fit.

Imports nothing of the package but its errors, so that the actor's pretrained folders
(:mod:`l1flow_rl.export.folder`) and the training checkpoints (:mod:`l1flow_rl.workspace.checkpoint`)
share it without importing each other.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from l1flow_rl.errors import CheckpointMismatchError

__all__ = ["load_state_into"]


def load_state_into(actor: torch.nn.Module, weights: Mapping[str, torch.Tensor], path: str = "") -> None:
    """``load_state_dict`` with a message that lists missing, unexpected and mis-shaped entries."""
    own = actor.state_dict()
    missing = sorted(set(own) - set(weights))
    unexpected = sorted(set(weights) - set(own))
    shapes = [
        f"{k}: checkpoint {tuple(weights[k].shape)} vs model {tuple(own[k].shape)}"
        for k in sorted(set(own) & set(weights))
        if weights[k].shape != own[k].shape
    ]
    if missing or unexpected or shapes:
        parts = []
        if shapes:
            parts.append("shape mismatches:\n    " + "\n    ".join(shapes[:10]))
        if missing:
            parts.append(f"missing from checkpoint: {missing[:10]}")
        if unexpected:
            parts.append(f"not in model: {unexpected[:10]}")
        raise CheckpointMismatchError(
            f"checkpoint {path!r} does not fit the network:\n  " + "\n  ".join(parts)
        )
    actor.load_state_dict(weights)
