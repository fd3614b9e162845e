"""Demonstration sources (scripted experts and planners), registered per simulator.

    from l1flow_rl.experts import ensure_demos
    path = ensure_demos(load_task_config("maniskill_pushcube"), num=100, data_dir="data")

The data layer (:mod:`l1flow_rl.data`) reads what these write; it does not know how they were made.
"""

from l1flow_rl.experts import registry
from l1flow_rl.experts.registry import *  # noqa: F403  (its public names, listed once in its __all__)

__all__ = list(registry.__all__)
