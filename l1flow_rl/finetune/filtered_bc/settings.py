"""Filtered BC's settings block, ``finetune.filtered_bc``."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["FilteredBCSettings"]


@dataclass
class FilteredBCSettings:
    """The L1 Flow loss on demonstrations and successful online episodes (``finetune.lr``,
    ``finetune.batch_size`` and the ``online`` block set its schedule)."""

    # leave the chunk steps padded past an episode's end out of the loss. An online success ends the
    # episode at the first step inside the goal while the arm still moves toward it, and delta
    # control pads "no motion" after the end: a false "stop here" at the threshold, where PickCube's
    # fine-tuned policy then parks short of the goal (benchmarks/results/diagnose_pickcube_mixed50b.json);
    # masked, with online.action_noise=0.02, the same start fine-tunes further than unmasked
    # (benchmarks/results/finetune_online_maniskill_pickcube_mixed50b_filtered_bc_an0p02_mask_100k.json).
    # Off by default: absolute control (Can) pads by holding the last target, a true label, and is not
    # measured masked.
    mask_padding: bool = False
