"""Filtered behaviour cloning: the flow's own loss on successful episodes, no critic; the flow acts.

The whole algorithm: ``loss.py`` (its TorchRL loss), ``settings.py`` (its block
``finetune.filtered_bc``), ``algorithm.py`` (``ALGORITHM``: the builder and what the loop needs); its
preset is ``configs/finetune/filtered_bc.yaml``.
"""

from l1flow_rl.finetune.filtered_bc.algorithm import ALGORITHM

__all__ = ["ALGORITHM"]
