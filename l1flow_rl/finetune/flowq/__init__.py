"""flow-Q: the L1 Flow policy's 2-NFE sampler as its own actor, climbing the chunk critics.

FQL distils a one-step actor because its flow needs ~10 steps to sample; L1 Flow samples in 2, so the
Q gradient goes through both network calls at the cost of about one extra forward and backward. The
actor is a trainable copy of the BC flow (it starts exactly at the BC policy) held near the frozen
BC flow's chunk for the same noise.

The whole algorithm: ``loss.py`` (its TorchRL loss), ``settings.py`` (its block ``finetune.flowq``),
``algorithm.py`` (``ALGORITHM``: the builder and what the loop needs); the acting module is the
trained flow itself (an :class:`~l1flow_rl.L1FlowActor`); its preset is ``configs/finetune/flowq.yaml``.
"""

from l1flow_rl.finetune.flowq.algorithm import ALGORITHM

__all__ = ["ALGORITHM"]
