"""Q-chunking (QC, ColinQiyangLi/qc): best-of-N flow proposals under chunk critics.

The whole algorithm: ``loss.py`` (its TorchRL loss), ``actor.py`` (its acting module), ``settings.py``
(its block ``finetune.qc``), ``algorithm.py`` (``ALGORITHM``: the builder and what the loop needs); its
preset is ``configs/finetune/qc.yaml``.
"""

from l1flow_rl.finetune.qc.algorithm import ALGORITHM

__all__ = ["ALGORITHM"]
