"""Demonstrations: how many to make (``demos``) and where data comes from (``data``)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["PADDING_RULES", "DataConfig", "DemosConfig"]


@dataclass
class DemosConfig:
    """Demonstration generation (ManiSkill motion planning, then replay into obs/control mode)."""

    num: int = 100
    # Give up when this many planner attempts in a row fail (a task whose planner never succeeds).
    max_consecutive_failures: int = 50
    seed: int = 0


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
    path: str | None = None
    padding: str = "maniskill"  # maniskill | diffusion_policy (PADDING_RULES)
