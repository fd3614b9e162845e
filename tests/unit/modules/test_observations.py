"""The observation reader the policy (and the critics) take their inputs through."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from l1flow_rl import L1FlowActor
from l1flow_rl.modules.observations import STATE_KEY, read_observations
from l1flow_rl.utils.value_checks import skip_value_checks

SHAPES = {"state": (4,), "rgb": (3, 8, 8)}


def _obs(batch=(2, 3), horizon=2, image_dtype=torch.uint8) -> TensorDict:
    return TensorDict(
        {
            "state": torch.randn(*batch, horizon, 4, dtype=torch.float64),
            "rgb": torch.zeros(*batch, horizon, 3, 8, 8, dtype=image_dtype),
        },
        batch_size=batch,
    )


def test_entries_flatten_to_n_to_and_keep_their_values():
    obs = _obs()
    flat, batch = read_observations(obs, SHAPES, 2, torch.float32)
    assert batch == (2, 3) and flat.batch_size == torch.Size([6, 2])
    assert flat["state"].dtype == torch.float32 and flat["rgb"].dtype == torch.uint8
    assert torch.equal(flat["state"], obs["state"].reshape(6, 2, 4).float())
    plain, batch = read_observations(torch.ones(5, 2, 4), {STATE_KEY: (4,)}, 2, torch.float64)
    assert batch == (5,) and plain[STATE_KEY].dtype == torch.float64
    unbatched, batch = read_observations(torch.ones(2, 4), {STATE_KEY: (4,)}, 2, torch.float32)
    assert batch == () and unbatched.batch_size == torch.Size([1, 2])


def test_mistakes_are_named():
    with pytest.raises(KeyError, match=r"\('observation', 'rgb'\) is missing"):
        read_observations(_obs().exclude("rgb"), SHAPES, 2, torch.float32)
    with pytest.raises(TypeError, match="'observation' is a tensor, but the encoder expects entries"):
        read_observations(torch.ones(2, 2, 4), SHAPES, 2, torch.float32)
    with pytest.raises(TypeError, match="must be a Tensor or a TensorDict, got list"):
        read_observations([1.0], SHAPES, 2, torch.float32)
    with pytest.raises(ValueError, match=r"'obs.state' must have shape \[\*B, 3, 4\]"):
        read_observations(_obs(), SHAPES, 3, torch.float32, key="obs")
    with pytest.raises(
        TypeError, match=r"'observation.rgb' is an image entry .* must be uint8, got torch.float32"
    ):
        read_observations(_obs(image_dtype=torch.float32), SHAPES, 2, torch.float32)
    mixed = TensorDict({"state": torch.ones(2, 2, 4), "rgb": torch.zeros(3, 2, 3, 8, 8, dtype=torch.uint8)})
    with pytest.raises(ValueError, match=r"'observation.rgb' has batch dims \(3,\), other .* \(2,\)"):
        read_observations(mixed, SHAPES, 2, torch.float32)


def test_non_finite_values_are_refused_unless_checks_are_skipped():
    obs = _obs()
    obs["state"][1, 2, 0, 3] = float("nan")
    with pytest.raises(ValueError, match=r"'observation\.state' contains NaN or Inf"):
        read_observations(obs, SHAPES, 2, torch.float32)
    with skip_value_checks():
        flat, _ = read_observations(obs, SHAPES, 2, torch.float32)
    assert flat["state"].isnan().sum() == 1


def test_the_policy_reads_through_it():
    actor = L1FlowActor.for_state(obs_dim=4, action_dim=2, down_dims=(16, 32))
    obs = torch.randn(3, 2, 4)
    expected, _ = read_observations(obs, {STATE_KEY: (4,)}, 2, torch.float32)
    assert torch.equal(actor.policy.as_obs_dict(obs)["state"], expected["state"])
    obs[0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match="contains NaN or Inf"):
        actor.policy.as_obs_dict(obs)
