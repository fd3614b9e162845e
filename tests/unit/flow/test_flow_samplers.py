"""Samplers: network evaluations per chunk, and DDPM/DDIM step for step against diffusers."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from l1flow_rl import L1FlowActor
from l1flow_rl.flow import (
    DDIMSampler,
    DDPMSampler,
    DiffusionSchedule,
    DirectSampler,
    EulerSampler,
    TwoStepSampler,
    VelocityEulerSampler,
    make_sampler,
)


@pytest.mark.parametrize(
    "sampler, nfe",
    [
        (TwoStepSampler(0.5), 2),
        (EulerSampler(10), 10),
        (VelocityEulerSampler(10), 10),
        (DDPMSampler(), 100),
        (DDIMSampler(16), 16),
        (DDIMSampler(8), 8),
        (DirectSampler(), 1),
    ],
    ids=repr,
)
def test_network_evaluations_per_chunk_and_one_encoder_call(sampler, nfe):
    actor = L1FlowActor.for_state(
        obs_dim=3, action_dim=2, down_dims=(16, 32), timestep_embed_dim=16, sampler=sampler
    )
    calls = {"net": 0, "encoder": 0}
    actor.policy.net.register_forward_hook(lambda *_: calls.__setitem__("net", calls["net"] + 1))
    actor.policy.encoder.register_forward_hook(lambda *_: calls.__setitem__("encoder", calls["encoder"] + 1))
    with torch.no_grad():
        out = actor(TensorDict({"observation": torch.randn(5, 2, 3)}, [5]))["action_chunk"]
    assert out.shape == (5, 8, 2)
    assert calls == {"net": nfe, "encoder": 1}
    assert sampler.nfe == nfe


def test_make_sampler_by_name():
    assert isinstance(make_sampler("two_step", t_first=0.4), TwoStepSampler)
    assert make_sampler("ddim", steps=10).nfe == 10
    with pytest.raises(ValueError, match="unknown sampler 'rk4'"):
        make_sampler("rk4")
    with pytest.raises(ValueError, match=r"steps must lie in \[1, 100\]"):
        DDIMSampler(101)


# -- diffusers equivalence -------------------------------------------------------------------------


def fake_epsilon(x: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """A fixed 'network': depends on the chunk and the step, large enough to trigger x0 clipping."""
    s = step.float().reshape(-1, 1, 1)
    return 0.8 * torch.sin(3.0 * x + 0.05 * s) + 0.3 * x


def recording(model, log):
    def denoise(x, step):
        log.append(x.clone())
        return model(x, step)

    return denoise


@pytest.fixture(scope="module")
def diffusers():
    return pytest.importorskip("diffusers")


def test_schedule_matches_diffusers(diffusers):
    ref = diffusers.DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2")
    ours = DiffusionSchedule(100)
    torch.testing.assert_close(ours.alphas_cumprod, ref.alphas_cumprod, rtol=1e-5, atol=1e-6)
    x0, noise, steps = torch.randn(6, 16, 2), torch.randn(6, 16, 2), torch.tensor([0, 1, 17, 50, 98, 99])
    torch.testing.assert_close(
        ours.add_noise(x0, noise, steps), ref.add_noise(x0, noise, steps), rtol=1e-5, atol=1e-5
    )


def test_ddpm_matches_diffusers_step_for_step(diffusers):
    ref = diffusers.DDPMScheduler(
        num_train_timesteps=100,
        beta_schedule="squaredcos_cap_v2",
        clip_sample=True,
        prediction_type="epsilon",
    )
    ref.set_timesteps(100)
    x_init = torch.randn(3, 16, 2, generator=torch.Generator().manual_seed(0))

    ours_log: list[torch.Tensor] = []
    ours = DDPMSampler()(
        recording(fake_epsilon, ours_log), x_init, generator=torch.Generator().manual_seed(1)
    )

    ref_log, x, gen = [], x_init.clone(), torch.Generator().manual_seed(1)  # same noise stream
    for step in ref.timesteps:
        ref_log.append(x.clone())
        eps = fake_epsilon(x, step.expand(x.shape[0]))
        x = ref.step(eps, step, x, generator=gen).prev_sample

    assert len(ours_log) == len(ref_log) == 100
    for i, (a, b) in enumerate(zip(ours_log, ref_log)):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4, msg=f"input to step {i}")
    torch.testing.assert_close(ours, x, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("k", [16, 10, 3])
def test_ddim_matches_diffusers_step_for_step(diffusers, k):
    ref = diffusers.DDIMScheduler(
        num_train_timesteps=100,
        beta_schedule="squaredcos_cap_v2",
        clip_sample=True,
        set_alpha_to_one=True,
        steps_offset=0,
        prediction_type="epsilon",
    )
    ref.set_timesteps(k)
    sampler = DDIMSampler(k)
    assert sampler.timesteps() == ref.timesteps.tolist()
    x_init = torch.randn(3, 16, 2, generator=torch.Generator().manual_seed(0))

    ours_log: list[torch.Tensor] = []
    ours = sampler(recording(fake_epsilon, ours_log), x_init)

    ref_log, x = [], x_init.clone()
    for step in ref.timesteps:
        ref_log.append(x.clone())
        x = ref.step(fake_epsilon(x, step.expand(x.shape[0])), step, x, eta=0.0).prev_sample

    assert len(ours_log) == len(ref_log) == k
    for i, (a, b) in enumerate(zip(ours_log, ref_log)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5, msg=f"input to step {i}")
    torch.testing.assert_close(ours, x, rtol=1e-5, atol=1e-5)
