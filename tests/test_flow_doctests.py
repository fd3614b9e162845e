"""The runnable examples in the core modules' docstrings."""

from __future__ import annotations

import doctest
import importlib

import pytest

MODULES = [
    "l1flow_rl.modules.actor",
    "l1flow_rl.finetune.best_of_n_actor",
    "l1flow_rl.networks.critic",
    "l1flow_rl.networks.mlp",
    "l1flow_rl.networks.registry",
    "l1flow_rl.config.network",
    "l1flow_rl.finetune.noise_actor",
    "l1flow_rl.finetune.one_step_actor",
    "l1flow_rl.modules.ema",
    "l1flow_rl.export.program",
    "l1flow_rl.flow.time",
    "l1flow_rl.objectives.chunk_critic",
    "l1flow_rl.objectives.diffusion",
    "l1flow_rl.objectives.dsrl",
    "l1flow_rl.objectives.dsrl_na",
    "l1flow_rl.objectives.filtered_bc",
    "l1flow_rl.objectives.finetune_registry",
    "l1flow_rl.objectives.flow_matching",
    "l1flow_rl.objectives.fql",
    "l1flow_rl.objectives.l1flow",
    "l1flow_rl.objectives.qc",
    "l1flow_rl.objectives.regression",
    "l1flow_rl.export.pretrained",
    "l1flow_rl.finetune.proposal_cache",
    "l1flow_rl.flow.karras",
    "l1flow_rl.objectives.edm",
    "l1flow_rl.objectives.consistency",
    "l1flow_rl.objectives.onedp_d",
    "l1flow_rl.objectives.onedp_s",
    "l1flow_rl.workspace.teacher",
]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0, f"{name} has no docstring example"
    assert result.failed == 0
