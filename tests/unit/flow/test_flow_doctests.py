"""The runnable examples in the core modules' docstrings."""

from __future__ import annotations

import doctest
import importlib

import pytest

MODULES = [
    "l1flow_rl.modules.actor",
    "l1flow_rl.modules.noisy_chain",
    "l1flow_rl.networks.critic",
    "l1flow_rl.networks.mlp",
    "l1flow_rl.networks.registry",
    "l1flow_rl.config.network",
    "l1flow_rl.modules.ema",
    "l1flow_rl.export.program",
    "l1flow_rl.flow.time",
    "l1flow_rl.objectives.diffusion",
    "l1flow_rl.objectives.flow_matching",
    "l1flow_rl.objectives.l1flow",
    "l1flow_rl.objectives.regression",
    "l1flow_rl.export.pretrained",
    "l1flow_rl.finetune.base",
    "l1flow_rl.finetune.registry",
    "l1flow_rl.finetune.proposal_cache",
    "l1flow_rl.flow.karras",
    "l1flow_rl.objectives.edm",
    "l1flow_rl.objectives.consistency",
    "l1flow_rl.objectives.onedp_d",
    "l1flow_rl.objectives.onedp_s",
    "l1flow_rl.workspace.teacher",
    "l1flow_rl.finetune.qc.actor",
    "l1flow_rl.finetune.qc.loss",
    "l1flow_rl.finetune.fql.actor",
    "l1flow_rl.finetune.fql.loss",
    "l1flow_rl.finetune.dsrl.actor",
    "l1flow_rl.finetune.dsrl.loss",
    "l1flow_rl.finetune.dsrl_na.loss",
    "l1flow_rl.finetune.filtered_bc.loss",
    "l1flow_rl.finetune.flowq.loss",
]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0, f"{name} has no docstring example"
    assert result.failed == 0
