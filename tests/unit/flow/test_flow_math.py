"""Flow maths: the time convention, the v-space weighting and the two-step sampler's identities."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from l1flow_rl import L1FlowActor, L1FlowLoss
from l1flow_rl.flow import (
    EulerSampler,
    TimestepDistribution,
    TwoStepSampler,
    VelocityEulerSampler,
    check_time,
    interpolate,
    sample_prediction_error,
    velocity_from_sample,
)


class FixedTimesteps(TimestepDistribution):
    """Hands out given times, so a loss can be recomputed by hand."""

    def __init__(self, t: torch.Tensor) -> None:
        self.t = t

    def sample(self, n, *, device="cpu", generator=None):
        assert n == self.t.numel()
        return self.t.to(device)


def nonlinear_denoiser(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """An arbitrary smooth 'network' of (x_t, t), to check identities that hold for any model."""
    return torch.tanh(1.7 * x + 0.3) * (1.0 + t.reshape(-1, 1, 1)) - 0.2 * x.square()


def test_interpolate_endpoints_and_midpoint():
    x0, x1 = torch.randn(3, 4, 2), torch.randn(3, 4, 2)
    torch.testing.assert_close(interpolate(x0, x1, torch.zeros(3)), x0)
    torch.testing.assert_close(interpolate(x0, x1, torch.ones(3)), x1)
    torch.testing.assert_close(interpolate(x0, x1, torch.tensor(0.25)), 0.75 * x0 + 0.25 * x1)


def test_velocity_from_exact_sample_is_the_straight_line_velocity():
    x0, x1, t = torch.randn(5, 8, 2), torch.randn(5, 8, 2), torch.rand(5) * 0.9
    torch.testing.assert_close(velocity_from_sample(x1, interpolate(x0, x1, t), t), x1 - x0)


@pytest.mark.parametrize("loss_type, power", [("l1", 1), ("mse", 2)])
def test_v_space_error_is_the_x_space_error_weighted_by_one_over_one_minus_t(loss_type, power):
    x0, x1, x1_hat = torch.randn(6, 8, 2), torch.randn(6, 8, 2), torch.randn(6, 8, 2)
    t = torch.tensor([0.0, 0.3, 0.5, 0.9, 0.96, 0.999])  # the last two hit the 0.05 clamp
    x_t = interpolate(x0, x1, t)
    # Computed independently from velocities: both share x_t, so their gap is (x1_hat - x1)/(1-t).
    v_hat, v = velocity_from_sample(x1_hat, x_t, t, 0.05), velocity_from_sample(x1, x_t, t, 0.05)
    diff = v_hat - v
    expected_v = diff.abs() if loss_type == "l1" else diff.square()
    got_v = sample_prediction_error(x1_hat, x1, t, loss_type, "v")
    torch.testing.assert_close(got_v, expected_v)
    weight = (1 - t).clamp_min(0.05).reshape(-1, 1, 1) ** -power
    torch.testing.assert_close(got_v, weight * sample_prediction_error(x1_hat, x1, t, loss_type, "x"))
    # the clamp caps the weight at 20 (or 400 for MSE)
    assert weight.max().item() == pytest.approx(20.0**power)


@pytest.mark.parametrize("loss_type, power", [("l1", 1), ("mse", 2)])
def test_l1flow_loss_in_v_space_equals_the_weighted_x_space_loss(loss_type, power):
    t = torch.tensor([0.1, 0.5, 0.97, 0.999])
    actor = L1FlowActor.for_state(obs_dim=3, action_dim=2, down_dims=(16, 32), timestep_embed_dim=16)
    td = TensorDict({"observation": torch.randn(4, 2, 3), "action_chunk": torch.rand(4, 16, 2) * 2 - 1}, [4])
    per_space = {}
    for space in ("x", "v"):
        loss_fn = L1FlowLoss(
            actor, timesteps=FixedTimesteps(t), loss_type=loss_type, loss_space=space, reduction="none"
        )
        torch.manual_seed(0)  # the same noise x0 for both spaces
        per_space[space] = loss_fn(td)["loss_l1flow"].detach()
    weight = (1 - t).clamp_min(0.05).reshape(-1, 1, 1) ** -power
    torch.testing.assert_close(per_space["v"], weight * per_space["x"])


def test_two_step_sampler_equals_two_euler_steps_for_any_model():
    x_init = torch.randn(4, 16, 3)
    two_step = TwoStepSampler(0.5)(nonlinear_denoiser, x_init)
    euler = EulerSampler(2)(nonlinear_denoiser, x_init)
    torch.testing.assert_close(two_step, euler)


def test_two_step_sampler_is_an_euler_step_to_t_first_then_a_direct_prediction():
    x_init, t1 = torch.randn(4, 16, 3), 0.3
    f0 = nonlinear_denoiser(x_init, torch.zeros(4))
    x_t1 = (1 - t1) * x_init + t1 * f0  # Euler from t=0 with v = f0 - x_init
    expected = nonlinear_denoiser(x_t1, torch.full((4,), t1))
    torch.testing.assert_close(TwoStepSampler(t1)(nonlinear_denoiser, x_init), expected)


@pytest.mark.parametrize(
    "sampler", [TwoStepSampler(0.5), TwoStepSampler(0.2), EulerSampler(2), EulerSampler(7)]
)
def test_sample_samplers_return_the_target_given_an_exact_model(sampler):
    target = torch.randn(4, 16, 3)

    def exact(x, t):  # a perfect sample predictor for a point-mass data distribution
        return target

    torch.testing.assert_close(sampler(exact, torch.randn(4, 16, 3)), target)


def test_velocity_euler_reaches_the_target_given_the_exact_velocity_field():
    target = torch.randn(4, 16, 3)

    def exact_velocity(x, t):  # straight-line velocity towards a point mass
        return (target - x) / (1 - t).reshape(-1, 1, 1)

    torch.testing.assert_close(VelocityEulerSampler(5)(exact_velocity, torch.randn(4, 16, 3)), target)


@pytest.mark.parametrize("bad", [torch.tensor([0.5, 1.2]), torch.tensor([-0.1, 0.5])])
def test_interpolate_rejects_time_outside_unit_interval(bad):
    with pytest.raises(ValueError, match=r"flow time 't' must lie in \[0, 1\]"):
        interpolate(torch.zeros(2, 4, 1), torch.zeros(2, 4, 1), bad)


def test_time_checks_name_the_problem():
    with pytest.raises(ValueError, match="'t' contains NaN or Inf"):
        check_time(torch.tensor([0.5, float("nan")]))
    with pytest.raises(ValueError, match=r"flow time 't' must have shape \[\] or \[2\], got \(2, 4\)"):
        interpolate(torch.zeros(2, 4, 1), torch.zeros(2, 4, 1), torch.rand(2, 4))
    with pytest.raises(
        ValueError, match=r"noise 'x0' must have the shape of 'x1' \(2, 4, 1\), got \(2, 4, 2\)"
    ):
        interpolate(torch.zeros(2, 4, 2), torch.zeros(2, 4, 1), torch.rand(2))


@pytest.mark.parametrize("t_first", [0.0, 1.0, 1.5])
def test_two_step_sampler_rejects_t_first_outside_open_interval(t_first):
    with pytest.raises(ValueError, match="t_first must lie strictly inside"):
        TwoStepSampler(t_first)


def test_loss_options_are_validated():
    actor = L1FlowActor.for_state(obs_dim=3, action_dim=2, down_dims=(16, 32), timestep_embed_dim=16)
    with pytest.raises(ValueError, match="loss_type must be 'l1' or 'mse'"):
        L1FlowLoss(actor, loss_type="huber")
    with pytest.raises(ValueError, match="loss_space must be 'x' or 'v'"):
        L1FlowLoss(actor, loss_space="eps")
    with pytest.raises(ValueError, match="unknown timestep distribution 'gauss'"):
        L1FlowLoss(actor, timesteps="gauss")
