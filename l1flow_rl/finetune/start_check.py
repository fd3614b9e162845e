"""The config check of ``l1flow-rl finetune`` that reads its start checkpoint: ``finetune.rl_horizon``
executes at most the start's ``policy.action_steps`` per chunk.

Apart from :mod:`l1flow_rl.finetune.registry` because it reads checkpoints, and the checkpoint module
imports the registry (to rebuild a fine-tuned run's acting module).
"""

from __future__ import annotations

from omegaconf import DictConfig

from l1flow_rl.errors import CheckpointReadError
from l1flow_rl.workspace.checkpoint import load_checkpoint

__all__ = ["start_problems"]


def start_problems(cfg: DictConfig, command: str) -> list[str]:
    """``finetune.rl_horizon`` against the start checkpoint's ``policy.action_steps``, read from its
    recorded config (its tensors mapped, not read); a checkpoint that cannot be read is left to the
    path check and to the job, which name it."""
    ft = cfg.get("finetune") if isinstance(cfg, DictConfig) else None
    if command != "finetune" or ft is None:
        return []
    horizon, path = ft.get("rl_horizon") or 0, cfg.get("checkpoint")
    if not path or not isinstance(horizon, int) or horizon < 1:  # 0: the start's action_steps
        return []
    try:
        steps = load_checkpoint(path, mmap=True)["config"]["policy"]["action_steps"]
    except (CheckpointReadError, KeyError, TypeError):
        return []
    if horizon <= steps:
        return []
    return [
        f"finetune.rl_horizon={horizon}: expected at most the checkpoint's policy.action_steps={steps} "
        f"(the actions executed per chunk; 0: all {steps})"
    ]
