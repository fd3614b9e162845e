"""Demonstrations: how many to make (``demos``) and where data comes from (``data``)."""

from __future__ import annotations

from dataclasses import dataclass

from omegaconf import OmegaConf

from l1flow_rl.config.path_fields import DATASET, path_field
from l1flow_rl.config.ranges import bounded

__all__ = [
    "PADDING_RULES",
    "QUALITIES",
    "QUALITY_LABELS",
    "DataConfig",
    "DemosConfig",
    "quality_problems",
    "shifted_replay_problems",
]

#: what ``demos.quality`` takes: expert demonstrations, or a labelled mix (l1flow_rl.experts.quality)
QUALITIES = ("expert", "mixed")
#: the per-episode labels of a mixed set, which ``data.labels`` selects from
QUALITY_LABELS = ("expert", "noisy", "recovered", "failed", "shifted")


@dataclass
class DemosConfig:
    """Demonstration generation (ManiSkill motion planning, then replay into obs/control mode)."""

    num: int = bounded(100, ge=1)
    # Give up when this many planner attempts in a row fail (a task whose planner never succeeds).
    max_consecutive_failures: int = bounded(50, ge=1)
    seed: int = bounded(0, ge=0, lt=2**32)
    quality: str = "expert"  # QUALITIES
    # Shifted replays of the successful episodes to fresh scenes, played in the simulator; the
    # successful ones join the set labelled "shifted" (l1flow_rl.experts.object_shift).
    shifted_replays: int = bounded(0, ge=0, zero="none")


#: how far chunks reach past an episode's ends (see l1flow_rl.data.chunks and
#: l1flow_rl.workspace.dataset.chunk_padding); what the padded actions are follows the control the
#: data record (delta: zero arm motion, absolute: the last action), not this choice:
#: maniskill: every step is a window's current step, up to H - To padded steps after the end;
#: diffusion_policy: To - 1 steps before the start and K - 1 after the end (K = policy.action_steps).
PADDING_RULES = ("maniskill", "diffusion_policy")


@dataclass
class DataConfig:
    """Where the demonstrations come from and how windows are cut from them."""

    # A user's own file or directory (robomimic .hdf5, Diffusion Policy .zarr, ManiSkill .h5,
    # LeRobot); None: the task's expert makes demos.num demonstrations under data_dir.
    path: str | None = path_field(None, kind=DATASET, commands=("train", "finetune"))
    padding: str = "maniskill"  # maniskill | diffusion_policy (PADDING_RULES)
    # Keep only episodes with these quality labels (QUALITY_LABELS, stored per episode by
    # demos.quality=mixed); None: every episode.
    labels: list[str] | None = None


def quality_problems(cfg, command: str) -> list[str]:
    """demos.quality is one of QUALITIES; data.labels lists known labels, at least one (a check of
    :data:`l1flow_rl.config.validate.BUILTIN_CHECKS`)."""
    problems = []
    quality = OmegaConf.select(cfg, "demos.quality", default="expert")
    if quality not in QUALITIES:
        problems.append(f"demos.quality={quality!r}: expected one of {list(QUALITIES)}")
    labels = OmegaConf.select(cfg, "data.labels", default=None)
    if labels is not None:
        unknown = [lb for lb in labels if lb not in QUALITY_LABELS]
        if unknown or not labels:
            problems.append(
                f"data.labels={list(labels)!r}: unknown label(s) {unknown}; expected a non-empty subset of "
                f"{list(QUALITY_LABELS)}"
            )
    problems += shifted_replay_problems(cfg)
    return problems


def shifted_replay_problems(cfg) -> list[str]:
    """demos.shifted_replays grows the expert's demonstrations, not a user's file (data.path); its
    range (>= 0) is declared on the field."""
    shifted = OmegaConf.select(cfg, "demos.shifted_replays", default=0) or 0
    path = OmegaConf.select(cfg, "data.path", default=None)
    if shifted and path:
        return [
            f"demos.shifted_replays={shifted}: it grows the expert's demonstrations, not data.path={path!r}; "
            "drop one of them"
        ]
    return []
