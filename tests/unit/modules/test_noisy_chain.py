"""The 2-NFE chain with learned noise (ReinFlow's route): its log-likelihood is the two Gaussian steps'
computed by hand, its noise stays in bounds, its gradient reaches both networks, and with the noise
bounded near 0 it is the deterministic 2-NFE sampler from the same start."""

from __future__ import annotations

import pytest
import torch
from torch.distributions import Normal

from l1flow_rl import L1FlowActor
from l1flow_rl.flow.samplers import EulerSampler
from l1flow_rl.modules.noisy_chain import NoiseStd, NoisyTwoStepChain


def policy(seed: int = 0):
    torch.manual_seed(seed)
    return L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32)).policy


def test_the_log_prob_is_the_two_gaussian_steps_by_hand():
    chain = NoisyTwoStepChain(policy(), min_std=0.05, max_std=0.3)
    torch.nn.init.normal_(chain.noise.mlp[-1].weight)  # a noise that depends on the state and the step
    obs = torch.randn(4, 2, 5)
    out = chain.sample(obs)
    p = chain.policy
    cond = p.encode(p.as_obs_dict(obs))
    t0, t1 = torch.zeros(4), torch.full((4,), 0.5)
    mean1 = 0.5 * out["x0"] + 0.5 * p.denoise(out["x0"], t0, cond)  # Euler to 0.5 with v = (f - x) / (1 - t)
    mean2 = p.denoise(out["x_mid"], t1, cond)
    std1, std2 = (chain.noise(cond, t).view(4, 16, 2) for t in (t0, t1))
    assert not torch.allclose(std1, std2)
    by_hand = Normal(mean1, std1).log_prob(out["x_mid"]).sum((1, 2)) + Normal(mean2, std2).log_prob(
        out["chunk"]
    ).sum((1, 2))
    torch.testing.assert_close(out["log_prob"], by_hand)
    torch.testing.assert_close(chain.log_prob(obs, out["x0"], out["x_mid"], out["chunk"]), by_hand)
    entropy = Normal(mean1, std1).entropy().sum((1, 2)) + Normal(mean2, std2).entropy().sum((1, 2))
    torch.testing.assert_close(chain.entropy(obs, out["x0"], out["x_mid"]), entropy)


def test_with_the_noise_bounded_near_zero_the_chain_is_the_2nfe_sampler():
    chain = NoisyTwoStepChain(policy(), min_std=1e-9, max_std=1e-9)
    obs, x0 = torch.randn(3, 2, 5), torch.randn(3, 16, 2)
    normalised = chain.policy.action_normalizer.normalize(chain.policy.sample_chunk(obs, noise=x0))
    torch.testing.assert_close(chain.sample(obs, x0)["chunk"], normalised, atol=1e-6, rtol=0)


def test_the_noise_stays_in_its_bounds_and_starts_midway():
    noise = NoiseStd(7, 32, min_std=0.08, max_std=0.14)
    torch.testing.assert_close(noise(torch.randn(5, 7), torch.rand(5)), torch.full((5, 32), 0.11))
    torch.nn.init.normal_(noise.mlp[-1].weight, std=100.0)
    std = noise(torch.randn(64, 7) * 10, torch.rand(64))
    assert std.min() >= 0.08 and std.max() <= 0.14 and std.std() > 0.01


def test_the_log_prob_gradient_reaches_the_flow_and_the_noise_networks():
    chain = NoisyTwoStepChain(policy())
    obs = torch.randn(4, 2, 5)
    with torch.no_grad():
        out = chain.sample(obs)
    chain.log_prob(obs, out["x0"], out["x_mid"], out["chunk"]).sum().backward()
    for name, module in (("flow", chain.policy.net), ("noise", chain.noise)):
        grads = [p.grad for p in module.parameters() if p.requires_grad]
        assert grads and all(g is not None for g in grads) and any(g.abs().sum() > 0 for g in grads), name


def test_bad_input_is_refused_naming_what_was_expected():
    with pytest.raises(ValueError, match=r"0 < min_std <= max_std, got 0\.2, 0\.1"):
        NoiseStd(4, 8, min_std=0.2, max_std=0.1)
    with pytest.raises(ValueError, match=r"0 < min_std <= max_std, got 0\.0"):
        NoiseStd(4, 8, min_std=0.0)
    with pytest.raises(
        TypeError, match="needs an L1 Flow policy \\(TwoStepSampler\\), got sampler EulerSampler"
    ):
        NoisyTwoStepChain(policy().with_sampler(EulerSampler(10)))
    with pytest.raises(
        ValueError, match=r"x0 must have shape \[N, pred_horizon, action_dim\] = \[3, 16, 2\]"
    ):
        NoisyTwoStepChain(policy()).sample(torch.randn(3, 2, 5), torch.randn(3, 8, 2))
