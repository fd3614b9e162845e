"""Test doubles: small, complete stand-ins that plug into the library's public extension points.

``point_mass`` is a whole simulator (a pure-torch 2-D point mass) with its scripted expert; it
registers both on import, the way a user's own simulator package would, and touches nothing else.
``continued_bc`` is a whole fine-tuning algorithm (plain continued BC) that ``finetune.algorithm``
names by its import path, with its preset in ``configs/finetune/`` (``--config-dir tests/doubles/configs``).
"""
