"""Diffusion steering with noise aliasing (DSRL-NA): SAC on a noise critic distilled from an action
critic; it acts through DSRL's noise actor.

The whole algorithm: ``loss.py`` (its TorchRL loss), ``settings.py`` (its block ``finetune.dsrl_na``),
``algorithm.py`` (``ALGORITHM``: the builder and what the loop needs); its preset is
``configs/finetune/dsrl_na.yaml``.
"""

from l1flow_rl.finetune.dsrl_na.algorithm import ALGORITHM

__all__ = ["ALGORITHM"]
