"""The policy group (``configs/policy/*.yaml``): the method (loss + sampler) and the shared UNet."""

from __future__ import annotations

from dataclasses import dataclass, field

from l1flow_rl.config.ranges import bounded

__all__ = ["PolicyConfig"]


@dataclass
class PolicyConfig:
    """Method and network. ``loss`` and ``sampler`` pick the method; the rest is the shared UNet."""

    name: str = "l1flow"
    loss: str = "l1flow"  # l1flow | flow_matching | diffusion | regression
    sampler: str = "two_step"  # two_step | euler | velocity_euler | ddpm | ddim | direct
    sampler_kwargs: dict = field(default_factory=dict)
    loss_kwargs: dict = field(default_factory=dict)
    # To, H, K: observed steps, predicted chunk, executed steps (To - 1 + K <= H)
    obs_horizon: int = bounded(2, ge=1)
    pred_horizon: int = bounded(16, ge=1)
    action_steps: int = bounded(8, ge=1)
    normalizer: str = "limits"  # actions: limits | gaussian | identity
    # Observations: limits blows up near-constant state dims (a 0.003-wide range scaled to [-1, 1]),
    # so states pass through raw by default, as in ManiSkill's baseline.
    obs_normalizer: str = "identity"  # limits | gaussian | identity
