"""Diffusion steering (DSRL-SAC, ajwagen/dsrl): SAC over the frozen flow's input noise.

The whole algorithm: ``loss.py`` (its TorchRL loss), ``actor.py`` (its acting module), ``settings.py``
(its block ``finetune.dsrl``), ``algorithm.py`` (``ALGORITHM``: the builder and what the loop needs);
its preset is ``configs/finetune/dsrl.yaml``.
"""

from l1flow_rl.finetune.dsrl.algorithm import ALGORITHM

__all__ = ["ALGORITHM"]
