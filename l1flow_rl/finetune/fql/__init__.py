"""Flow Q-learning (FQL, seohongpark/fql) on chunks: a one-step actor distilled from the flow climbs
the critics.

The whole algorithm: ``loss.py`` (its TorchRL loss), ``actor.py`` (its acting module), ``settings.py``
(its block ``finetune.fql``), ``algorithm.py`` (``ALGORITHM``: the builder and what the loop needs); its
preset is ``configs/finetune/fql.yaml``.
"""

from l1flow_rl.finetune.fql.algorithm import ALGORITHM

__all__ = ["ALGORITHM"]
