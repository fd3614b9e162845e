"""DSRL's settings block, ``finetune.dsrl`` (defaults: ajwagen/dsrl)."""

from __future__ import annotations

from dataclasses import dataclass

from l1flow_rl.config.ranges import bounded

__all__ = ["DSRLSettings"]


@dataclass
class DSRLSettings:
    noise_bound: float = bounded(1.5, gt=0)  # DSRL: |w| <= 1.5 (tanh-squashed)
    target_entropy: float = bounded(0.0)  # DSRL's configs; any number (an entropy target in nats)
    # SAC's automatic temperature (stable-baselines3, which DSRL uses) starts at 1, where the entropy
    # of the H x A noise (log pi sums one term per noise entry) swamps sparse rewards <= 1 in the soft
    # target; 1e-3 keeps the entropy term at the rewards' scale.
    init_alpha: float = bounded(1.0e-3, gt=0)
    # DSRL steps a chunk-wrapped env (one chunk = one MDP step, its rewards summed) under SB3's gamma:
    # finetune.gamma per chunk decision, 0.99 there; false: per env step (0.99^8 = 0.92 per chunk of 8)
    discount_per_chunk: bool = True
    # DSRL: 3 x 2048; 3 x 512 for the cost on 2 cores
    actor_hidden_dims: list[int] = bounded(lambda: [512, 512, 512], ge=1, each=True)
