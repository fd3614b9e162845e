"""examples/pretrained_inference.py runs a pretrained folder receding horizon, from its weights and from
its exported program, with the same actions."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

from l1flow_rl import L1FlowActor

EXAMPLE = Path(__file__).parents[3] / "examples" / "pretrained_inference.py"


def _example():
    spec = importlib.util.spec_from_file_location("pretrained_inference", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_example_acts_receding_horizon_from_weights_and_program_alike(tmp_path, capsys):
    example = _example()
    torch.manual_seed(0)
    actor = L1FlowActor.for_state(obs_dim=3, action_dim=2, down_dims=(16, 32)).eval()
    actor.policy.fit_normalizers(torch.randn(64, 3), torch.rand(64, 2) * 10)
    folder = actor.save_pretrained(tmp_path / "policy", program=True)
    config = example.read_pretrained_config(folder)

    actions, chunks = example.run(folder, example.synthetic_stream(config, 20), seed=3)
    assert actions.shape == (20, 2) and chunks == 3  # K = 8: plans at steps 0, 8 and 16
    again, _ = example.run(folder, example.synthetic_stream(config, 20), program=True, seed=3)
    assert torch.equal(again, actions)

    # the first chunk by hand: the first observation repeated To times, the run's first noise draw
    first = next(example.synthetic_stream(config, 1))["state"]
    noise = torch.randn(1, 16, 2, generator=torch.Generator().manual_seed(3))
    want = actor.policy(first.expand(1, 2, 3), noise=noise)[0]
    assert torch.equal(actions[:8], want)
    assert not torch.equal(actions[8:16], want)  # the second chunk is planned from newer observations

    assert example.main([str(folder), "--steps", "9", "--program"]) == 0
    assert "9 actions from 2 chunks" in capsys.readouterr().out
