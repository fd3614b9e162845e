"""Fine-tuning algorithm ``continued_bc``, from outside the library: plain continued behaviour cloning
(the flow's own L1 Flow loss on every window, demonstrations and online episodes alike).

The whole of what adding an algorithm takes: this folder (``loss.py``, ``settings.py``,
``algorithm.py`` with ``ALGORITHM``) and its preset, ``tests/doubles/configs/finetune/continued_bc.yaml``
(``finetune.algorithm: doubles.continued_bc``), found with ``l1flow-rl finetune --config-dir
tests/doubles/configs finetune=continued_bc``. Nothing in the library changes.
"""

from .algorithm import ALGORITHM

__all__ = ["ALGORITHM"]
