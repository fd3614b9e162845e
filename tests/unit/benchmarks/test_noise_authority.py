"""The noise-authority benchmark: its statistics on tiny randomly initialised policies whose dependence on
the input noise is known (none, through the network, or the identity), and its CLI's argument errors."""

from __future__ import annotations

import pytest
import torch

from benchmarks.finetune.bench_noise_authority import BOUND, STATISTICS, action_groups, main, noise_authority
from l1flow_rl.flow.samplers import DDPMSampler, VelocityEulerSampler
from l1flow_rl.modules.actor import L1FlowActor

N, A = 6, 2


def _actor(**kwargs) -> L1FlowActor:
    torch.manual_seed(0)
    return L1FlowActor.for_state(obs_dim=5, action_dim=A, down_dims=(16, 32), **kwargs).eval()


def _obs() -> torch.Tensor:
    return torch.randn(N, 2, 5, generator=torch.Generator().manual_seed(1))


def test_statistics_have_one_value_per_action_dim_in_both_units():
    out = noise_authority(_actor().policy, _obs(), draws=3)
    assert out["per_step_noise"] is False
    for unit in ("env", "normalized"):
        assert set(out[unit]) == set(STATISTICS)
        assert all(v.shape == (A,) for v in out[unit].values())
    assert out["authority"].shape == (A,)
    assert torch.allclose(out["authority"], out["env"]["std_noise"] / out["env"]["std_states"])


def test_a_network_blind_to_its_input_chunk_has_no_authority_and_a_seeing_one_has_some():
    actor = _actor()
    seeing = noise_authority(actor.policy, _obs(), draws=4)
    first = actor.policy.net.down[0][0]  # the only block that reads x_t: its conv and its residual
    with torch.no_grad():
        first.block1[0].weight.zero_()
        first.residual.weight.zero_()
    blind = noise_authority(actor.policy, _obs(), draws=4)
    assert (blind["env"]["std_states"] > 1e-4).all()  # the observation still moves the chunk
    for key in ("std_noise", "std_noise_corners", "std_noise_wide", "mean_abs_shift"):
        assert blind["env"][key].abs().max() < 1e-6
        assert (seeing["env"][key] > 1e-4).all()


def test_a_flow_with_zero_velocity_returns_its_noise_so_the_spreads_are_the_draws():
    actor = _actor(sampler=VelocityEulerSampler(steps=2))
    with torch.no_grad():
        for p in actor.policy.net.head.parameters():
            p.zero_()
    out = noise_authority(actor.policy, _obs(), draws=16)["normalized"]  # identity normaliser
    assert ((out["std_noise"] > 0.7) & (out["std_noise"] < 1.0)).all()  # N(0, 1) clipped to 1.5
    assert ((out["std_noise_corners"] > 0.85 * BOUND) & (out["std_noise_corners"] < 1.1 * BOUND)).all()
    assert ((out["std_noise_wide"] > 2.5) & (out["std_noise_wide"] < 3.3)).all()
    assert out["std_states"].abs().max() == 0  # w = 0 gives 0 everywhere


def test_ddpm_per_step_noise_is_held_fixed_and_measured_apart():
    out = noise_authority(_actor(sampler=DDPMSampler(num_train_timesteps=5)).policy, _obs(), draws=3)
    assert out["per_step_noise"] is True
    assert (out["env"]["std_step_noise"] > 0).all() and (out["env"]["std_noise"] > 0).all()


def test_action_groups_put_position_first_and_the_gripper_last():
    assert action_groups(2) == {"position": [0, 1]}
    assert action_groups(4) == {"position": [0, 1, 2], "gripper": [3]}
    assert action_groups(7) == {"position": [0, 1, 2], "rotation": [3, 4, 5], "gripper": [6]}


@pytest.mark.parametrize(
    ("item", "said"), [("best.pt", "is not NAME=PATH"), ("a=/no/such/best.pt", "no file at /no/such/best.pt")]
)
def test_a_bad_checkpoint_argument_is_one_line_naming_it(item, said, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--checkpoint", item])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "--checkpoint" in err and item in err and said in err
