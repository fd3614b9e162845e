"""The training job's loss: padded steps leave the loss by default exactly where the data's control
pads them with a label the demonstrator never gave (delta control's "no motion")."""

import pytest
import torch
from tensordict import TensorDict

from l1flow_rl.workspace.build import build_actor, build_loss

POLICY = {
    "name": "l1flow",
    "loss": "l1flow",
    "sampler": "two_step",
    "sampler_kwargs": {"t_first": 0.5},
    "loss_kwargs": {"timesteps": "mixed", "loss_type": "l1", "loss_space": "x"},
    "obs_horizon": 2,
    "pred_horizon": 4,
    "action_steps": 2,
}
NETWORK = {"name": "mlp", "hidden_dims": [32, 32]}


def _actor():
    torch.manual_seed(0)
    return build_actor(POLICY, {"state": (3,)}, 2, None, NETWORK)


@pytest.mark.parametrize(("control", "masked"), [("delta", True), ("absolute", False), (None, False)])
def test_delta_control_masks_padding_by_default(control, masked):
    assert build_loss(_actor(), POLICY, control=control).mask_padding is masked


@pytest.mark.parametrize("control", ["delta", "absolute"])
@pytest.mark.parametrize("asked", [True, False])
def test_policy_loss_kwargs_win_over_the_default(control, asked):
    policy = {**POLICY, "loss_kwargs": {**POLICY["loss_kwargs"], "mask_padding": asked}}
    assert build_loss(_actor(), policy, control=control).mask_padding is asked


def test_the_default_changes_the_loss_only_through_padded_steps():
    actor = _actor()
    torch.manual_seed(1)
    td = TensorDict(
        {
            "observation": torch.randn(8, 2, 3),
            "action_chunk": torch.randn(8, 4, 2),
            "action_is_pad": torch.zeros(8, 4, dtype=torch.bool),
        },
        batch_size=[8],
    )
    losses = {}
    for control in ("delta", "absolute"):
        torch.manual_seed(2)
        losses[control] = build_loss(actor, POLICY, control=control)(td.clone())["loss_l1flow"]
    assert torch.equal(losses["delta"], losses["absolute"])  # nothing padded: the same loss
    td["action_is_pad"][:, -2:] = True
    td["action_chunk"][:, -2:] = 0.0  # delta control's "no motion" padding
    for control in ("delta", "absolute"):
        torch.manual_seed(2)
        losses[control] = build_loss(actor, POLICY, control=control)(td.clone())["loss_l1flow"]
    assert not torch.equal(losses["delta"], losses["absolute"])
