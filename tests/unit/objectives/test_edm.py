"""EDM-scheduled Diffusion Policy: Karras preconditioning, the Heun sampler and its NFE, the loss, the
consistency boundary condition, and re-scoring under the sampler swap."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from tensordict import TensorDict

from l1flow_rl import EDMLoss, L1FlowActor
from l1flow_rl.flow import ConsistencySampler, EDMHeunSampler, make_sampler
from l1flow_rl.flow.karras import KarrasPreconditioning, KarrasSchedule, heun_step
from l1flow_rl.flow.samplers import SamplerMismatchError


def _actor(sampler, **kwargs):
    return L1FlowActor.for_state(
        obs_dim=5, action_dim=2, down_dims=(16, 32), timestep_embed_dim=16, sampler=sampler, **kwargs
    )


def _batch(n=8):
    return TensorDict(
        {"observation": torch.randn(n, 2, 5), "action_chunk": torch.rand(n, 16, 2) * 2 - 1}, batch_size=[n]
    )


@pytest.mark.parametrize("sigma", [0.5, 2.0])
def test_preconditioning_matches_a_hand_computation(sigma):
    sd = 0.5
    # by hand: EDM's Table 1
    c_skip = sd**2 / (sigma**2 + sd**2)
    c_out = sigma * sd / math.sqrt(sigma**2 + sd**2)
    c_in = 1 / math.sqrt(sigma**2 + sd**2)
    c_noise = math.log(sigma) / 4
    got = KarrasPreconditioning(sigma_data=sd).scalings(torch.tensor(sigma, dtype=torch.float64))
    assert [float(c) for c in got] == pytest.approx([c_skip, c_out, c_in, c_noise], rel=1e-12)
    if sigma == 0.5:  # the numbers themselves, once
        assert [round(float(c), 4) for c in got] == [0.5, 0.3536, 1.4142, -0.1733]
    weight = KarrasPreconditioning(sigma_data=sd).loss_weight(torch.tensor(sigma, dtype=torch.float64))
    assert float(weight) == pytest.approx((sigma**2 + sd**2) / (sigma * sd) ** 2, rel=1e-12)

    # D(x) = c_skip x + c_out F(c_in x, c_noise): the network sees c_in x and c_noise
    seen = {}

    def net(x_in, c):
        seen["x_in"], seen["c"] = x_in.clone(), c.clone()
        return torch.full_like(x_in, 3.0)

    x = torch.randn(2, 4, 2, dtype=torch.float64)
    out = KarrasPreconditioning(sd).denoise(net, x, torch.tensor([sigma, sigma], dtype=torch.float64))
    assert torch.allclose(out, c_skip * x + c_out * 3.0)
    assert torch.allclose(seen["x_in"], c_in * x)
    assert seen["c"].tolist() == pytest.approx([c_noise, c_noise])


def test_the_rho_schedule_runs_from_sigma_max_to_sigma_min():
    sigmas = KarrasSchedule(0.002, 80.0, 7.0).sigmas(18)
    assert sigmas[0].item() == pytest.approx(80.0) and sigmas[-1].item() == pytest.approx(0.002)
    assert (sigmas[1:] < sigmas[:-1]).all()
    mid = (80 ** (1 / 7) + 0.5 * (0.002 ** (1 / 7) - 80 ** (1 / 7))) ** 7  # EDM eq. 5 at i = (n-1)/2
    assert KarrasSchedule().sigmas(3)[1].item() == pytest.approx(mid, rel=1e-5)


@pytest.mark.parametrize("steps", [1, 2, 10, 18])
def test_heun_sampler_counts_2n_minus_1_network_evaluations(steps):
    calls = []

    def denoise(x, t):
        calls.append(t.clone())
        return torch.zeros_like(x)

    sampler = EDMHeunSampler(steps)
    sampler(denoise, torch.randn(3, 16, 2))
    assert len(calls) == sampler.nfe == 2 * steps - 1
    # the network's time input is c_noise = ln(sigma) / 4 at every level of the schedule
    levels = KarrasSchedule().sigmas(steps)
    first_evals = sorted({round(float(t[0]), 5) for t in calls})
    assert first_evals == sorted({round(math.log(float(s)) / 4, 5) for s in levels})


def test_heun_with_an_exact_denoiser_lands_on_the_data():
    # Data at a single point: the exact denoiser is that point, the ODE solution ends there.
    target = torch.tensor([0.3, -0.7])

    def denoiser(x, sigma):
        return target.expand_as(x)

    x = torch.randn(4, 16, 2) * 80
    levels = torch.cat([KarrasSchedule().sigmas(5), torch.zeros(1)])
    for i, (s, s_next) in enumerate(itertools.pairwise(levels)):
        x = heun_step(denoiser, x, s, s_next, to_zero=i == len(levels) - 2)
    assert torch.allclose(x, target.expand_as(x), atol=1e-5)


def test_consistency_preconditioning_is_the_identity_at_sigma_min():
    # CP's boundary condition: c_skip(sigma_min) = 1, c_out(sigma_min) = 0, whatever the network
    sampler = ConsistencySampler(sigma_min=0.02)
    c_skip, c_out, _, _ = sampler.preconditioning.scalings(torch.tensor(0.02))
    assert (float(c_skip), float(c_out)) == (1.0, 0.0)
    actor = _actor(sampler, timestep_scale=1000.0)
    x = torch.randn(3, 16, 2)
    cond = torch.randn(3, actor.policy.net.global_cond_dim)
    out = sampler.preconditioning.denoise(
        lambda xin, c: actor.policy.denoise(xin, c, cond), x, torch.full((3,), 0.02)
    )
    assert torch.equal(out, x)
    assert not torch.allclose(
        sampler.preconditioning.denoise(
            lambda xin, c: actor.policy.denoise(xin, c, cond), x, torch.tensor(1.0)
        ),
        x,
    )


def test_consistency_sampler_chains_cp_bins_and_counts_one_evaluation_per_step():
    assert ConsistencySampler(3).chain_bins() == [27, 54]  # CP's 3-step chain on 80 bins
    calls = []

    def denoise(x, t):
        calls.append(float(t[0]))
        return torch.zeros_like(x)

    sampler = ConsistencySampler(3)
    sampler(denoise, torch.randn(2, 16, 2))
    bins = sampler.bin_sigmas()
    assert len(calls) == sampler.nfe == 3
    assert calls == pytest.approx([math.log(float(bins[b])) / 4 for b in (0, 27, 54)], rel=1e-5)


def test_edm_loss_trains_and_weights_by_edm_lambda():
    torch.manual_seed(0)
    actor = _actor(EDMHeunSampler(4), timestep_scale=1000.0)
    loss_fn = EDMLoss(actor)
    out = loss_fn(_batch())
    assert set(out.keys()) == {"loss_edm", "sigma_median", "x_error_l1"}
    out["loss_edm"].backward()
    assert all(p.grad is not None for p in actor.policy.net.parameters() if p.requires_grad)
    assert not out["sigma_median"].requires_grad

    # The element-wise loss is lambda(sigma) |D - x0|^2: check it with the same draws by hand.
    td = _batch(4)
    torch.manual_seed(1)
    got = EDMLoss(actor, reduction="none")(td)["loss_edm"]
    torch.manual_seed(1)
    x0 = td["action_chunk"]  # the identity normaliser: already normalised
    sigma = (torch.randn(4) * 1.2 - 1.2).exp()
    noisy = x0 + sigma.reshape(-1, 1, 1) * torch.randn_like(x0)
    pre = actor.sampler.preconditioning
    cond = actor.policy.encode(actor.policy.as_obs_dict(td["observation"]))
    d = pre.denoise(lambda x, c: actor.policy.denoise(x, c, cond), noisy, sigma)
    assert torch.allclose(got, pre.loss_weight(sigma).reshape(-1, 1, 1) * (d - x0).square(), rtol=1e-4)


def test_the_loss_refuses_an_actor_sampled_for_another_prediction():
    with pytest.raises(ValueError, match="EDMHeunSampler"):
        EDMLoss(_actor(make_sampler("ddpm")))


def test_rescoring_an_edm_network_at_other_step_counts_goes_through_the_sampler_swap():
    actor = _actor(EDMHeunSampler(18), timestep_scale=1000.0)
    assert actor.sampler.nfe == 35
    assert actor.with_sampler("edm_heun", steps=10).sampler.nfe == 19
    one = actor.with_sampler("edm_heun", steps=1)
    assert one.sampler.nfe == 1 and one.policy.net is actor.policy.net
    chunk = one(TensorDict({"observation": torch.randn(2, 2, 5)}, batch_size=[2]))["action_chunk"]
    assert chunk.shape == (2, 8, 2) and chunk.abs().max() <= 1.0  # clipped to the action range
    with pytest.raises(SamplerMismatchError, match="edm_heun"):
        actor.with_sampler("ddim", steps=4)
    with pytest.raises(SamplerMismatchError, match="sigma_data"):
        actor.with_sampler("edm_heun", sigma_data=1.0)


def test_policy_edm_composes_and_a_wrong_sampler_is_refused_at_config_time():
    from l1flow_rl.commands.cli import compose_config
    from l1flow_rl.config.validate import ConfigValidationError

    cfg = compose_config(["policy=edm"])
    assert (cfg.policy.loss, cfg.policy.sampler, cfg.network.timestep_scale) == ("edm", "edm_heun", 1000.0)
    assert make_sampler(cfg.policy.sampler, **cfg.policy.sampler_kwargs).nfe == 35
    with pytest.raises(
        ConfigValidationError, match=r"policy\.sampler='edm_consistency' reads a 'consistency'"
    ):
        compose_config(["policy=edm", "policy.sampler=edm_consistency"])
    with pytest.raises(ConfigValidationError, match=r"steps must be >= 1"):
        compose_config(["policy=edm", "policy.sampler_kwargs.steps=0"])


def test_the_heun_sampler_exports_as_one_program():
    # the last step's Euler-only form is decided by the step count, not by reading a value back
    from l1flow_rl.export.program import DeployablePolicy, example_inputs

    actor = _actor(EDMHeunSampler(3), timestep_scale=1000.0).eval()
    program = torch.export.export(DeployablePolicy(actor), example_inputs(actor), strict=False)
    obs, noise = torch.randn(1, 2, 5), torch.randn(1, 16, 2)
    assert torch.allclose(program.module()(obs, noise), actor.policy(obs, noise=noise), atol=1e-5)
