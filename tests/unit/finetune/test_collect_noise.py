"""Exploration noise while collecting (``online.action_noise``): every executed and stored action is
the policy's plus Gaussian noise of that std, inside the action bounds; without it, the policy's own."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from doubles.point_mass import POINT_MASS_TASK
from omegaconf import OmegaConf
from tensordict.nn import TensorDictModule

from l1flow_rl.finetune.collect import OnlineCollector

CHUNK = 4


def _constant_chunks(value: float) -> TensorDictModule:
    def chunk(observation: torch.Tensor) -> torch.Tensor:
        return torch.full((*observation.shape[:-2], CHUNK, 2), value)

    return TensorDictModule(chunk, in_keys=["observation"], out_keys=["action_chunk"])


def _collect(action_noise: float, value: float) -> torch.Tensor:
    task = dataclasses.asdict(dataclasses.replace(POINT_MASS_TASK, max_episode_steps=200))
    cfg = OmegaConf.create(
        {
            "task": task,
            "policy": {"obs_horizon": 2, "action_steps": CHUNK},
            "online": {"num_envs": 2, "frames_per_round": 400, "env_seed": 0, "action_noise": action_noise},
        }
    )
    torch.manual_seed(0)
    with OnlineCollector(cfg, _constant_chunks(value), torch.device("cpu")) as collector:
        return collector.collect(0)["action"]


def test_without_noise_the_stored_actions_are_the_policys():
    actions = _collect(0.0, 0.3)
    assert torch.equal(actions, torch.full_like(actions, 0.3))


def test_noise_of_the_asked_std_is_added_to_every_action_and_kept_in_bounds():
    actions = _collect(0.2, 0.3)
    assert actions.shape[-1] == 2 and actions.numel() == 800
    noise = actions - 0.3
    assert (noise != 0).all()  # every step, not one per chunk
    assert noise.mean().abs() < 0.03 and noise.std() == pytest.approx(0.2, rel=0.1)
    # consecutive steps of a chunk draw independent noise
    flat = noise.reshape(-1, 2)
    assert torch.corrcoef(torch.stack([flat[:-1, 0], flat[1:, 0]]))[0, 1].abs() < 0.15
    # near the bound the noisy action is projected into [-1, 1], never past it
    edge = _collect(0.2, 0.95)
    assert edge.max() == 1.0 and edge.min() >= -1.0 and (edge == 1.0).float().mean() > 0.3
