"""Fine-tuning a trained BC policy with rewards: the loop, and one folder per algorithm.

* :mod:`.base`: the chunk critic's TD loss (:class:`~l1flow_rl.finetune.base.ChunkCriticLoss`) and the
  protocol the loop talks to (:class:`~l1flow_rl.finetune.base.FinetuneAlgorithm`,
  :class:`~l1flow_rl.finetune.base.Learner`).
* :mod:`.loop`: ``l1flow-rl finetune``; :mod:`.buffers` (demonstration and online chunk windows with RL
  targets), :mod:`.collect` (the online rounds), :mod:`.proposal_cache` (a frozen flow's proposals,
  drawn once).
* :mod:`.registry`: ``finetune.algorithm`` -> the algorithm, found by import.
* One folder per algorithm: ``qc``, ``fql``, ``flowq``, ``dsrl``, ``dsrl_na``, ``filtered_bc``; each
  holds its loss (``loss.py``), its acting module (``actor.py``, where it has its own), its settings
  block (``settings.py``) and its builder (``algorithm.py``, ``ALGORITHM``).

Add a fine-tuning algorithm (one folder plus one preset; nothing else changes):

1. A folder ``l1flow_rl/finetune/<name>/``, or a package of your own on the path: its TorchRL loss, its
   acting module, a settings dataclass (numeric fields declared with
   :func:`~l1flow_rl.config.ranges.bounded`), and ``ALGORITHM``, an instance of a
   :class:`~l1flow_rl.finetune.base.FinetuneAlgorithm` subclass with ``name``, ``settings`` and
   ``build(flow, cfg, seed=0)`` (the loss; its ``actor`` acts).
2. A preset ``configs/finetune/<name>.yaml`` (or one in ``--config-dir``) with
   ``finetune.algorithm: <name>`` (your package: its import path, ``my_package.<name>``), the block
   ``finetune.<name>`` and the schedule (``online``, ``offline``).

The config validator then checks the block's keys, types and ranges before any work, and
``l1flow-rl finetune`` / ``l1flow-rl eval`` find the algorithm by that name. ``tests/doubles/continued_bc``
is a complete example.
"""
