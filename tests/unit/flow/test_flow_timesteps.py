"""Timestep distributions: moments, support, seeded reproducibility, bad parameters."""

from __future__ import annotations

import math

import pytest
import torch

from l1flow_rl.flow import (
    BetaTimesteps,
    MixedLogitNormalTimesteps,
    UniformTimesteps,
    make_timesteps,
)

N = 400_000


def logit_normal_variance(mean: float = 0.0, std: float = 1.0) -> float:
    """Var[sigmoid(Z)], Z ~ N(mean, std^2), by quadrature on a fine grid (no closed form exists)."""
    z = torch.linspace(-12.0, 12.0, 200_001, dtype=torch.float64)
    density = torch.exp(-0.5 * ((z - mean) / std) ** 2) / (std * math.sqrt(2 * math.pi))
    dz = float(z[1] - z[0])
    s = torch.sigmoid(z)
    m1 = float((s * density).sum() * dz)
    m2 = float((s.square() * density).sum() * dz)
    return m2 - m1**2


def draw(dist, n=N, seed=0):
    return dist.sample(n, generator=torch.Generator().manual_seed(seed)).double()


def test_mixed_logit_normal_moments():
    t = draw(MixedLogitNormalTimesteps())
    v_ln = logit_normal_variance()
    assert 0.0433 < v_ln < 0.0435  # Var[sigmoid(N(0, 1))] ~ 0.04338, checked by Monte Carlo
    # Both mixture parts have mean 1/2, so the variance is the mixture of the two variances.
    expected_var = 0.99 * v_ln + 0.01 / 12
    assert t.mean().item() == pytest.approx(0.5, abs=0.002)
    assert t.var().item() == pytest.approx(expected_var, rel=0.02)
    assert t.min() > 0.0 and t.max() < 1.0


def _normal_cdf(x: float) -> float:
    return 0.5 * math.erfc(-x / math.sqrt(2))


def _logit(p: float) -> float:
    return math.log(p / (1 - p))


def _assert_binomial(count: int, n: int, p: float, z_max: float = 4.0) -> None:
    """``count`` successes in ``n`` draws are consistent with probability ``p`` (|z| < z_max)."""
    z = (count - n * p) / math.sqrt(n * p * (1 - p))
    assert abs(z) < z_max, f"{count} of {n} draws, expected {n * p:.1f} (p={p:.3g}): z={z:.1f}"


def test_mixed_law_tails_match_the_exact_probabilities():
    # Exact: P(t < a) = (1 - p_u) * Phi(logit(a)) + p_u * a for t = sigmoid(N(0, 1)) replaced by U(0, 1)
    # with probability p_u. At a = 0.01 the logit-normal part alone gives Phi(-4.595) = 2.16e-6, so the
    # 1 % uniform share lifts the tail about 50-fold, to 1.02e-4; at a = 0.001 the uniform share is
    # all that is left (1e-5 against 2.5e-12).
    p_ln = _normal_cdf(_logit(0.01))
    assert p_ln == pytest.approx(2.1625e-6, rel=1e-3)
    n = 4_000_000
    t = MixedLogitNormalTimesteps().sample(n, generator=torch.Generator().manual_seed(0))
    _assert_binomial(int((t < 0.01).sum()), n, 0.99 * p_ln + 0.01 * 0.01)  # 1.021e-4
    _assert_binomial(int((t > 0.99).sum()), n, 0.99 * p_ln + 0.01 * 0.01)
    _assert_binomial(int((t < 0.001).sum()), n, 0.99 * _normal_cdf(_logit(0.001)) + 0.01 * 0.001)


def test_pure_logit_normal_tail_matches_the_exact_probability():
    p_ln = _normal_cdf(_logit(0.01))  # 2.16e-6 per tail
    n = 10_000_000
    t = MixedLogitNormalTimesteps(p_uniform=0.0).sample(n, generator=torch.Generator().manual_seed(1))
    _assert_binomial(int(((t < 0.01) | (t > 0.99)).sum()), n, 2 * p_ln)  # about 43 of 10 million


def test_pure_logit_normal_and_pure_uniform_ends_of_the_mixture():
    t = draw(MixedLogitNormalTimesteps(p_uniform=0.0))
    assert t.var().item() == pytest.approx(logit_normal_variance(), rel=0.02)
    t = draw(MixedLogitNormalTimesteps(p_uniform=1.0))
    assert t.var().item() == pytest.approx(1 / 12, rel=0.02)


def test_uniform_moments():
    t = draw(UniformTimesteps())
    assert t.mean().item() == pytest.approx(0.5, abs=0.002)
    assert t.var().item() == pytest.approx(1 / 12, rel=0.02)
    assert t.min() >= 0.0 and t.max() < 1.0


def test_beta_moments_weighted_towards_noise():
    t = draw(BetaTimesteps())  # 0.999 * Beta(1, 1.5)
    a, b, c = 1.0, 1.5, 0.999
    mean = c * a / (a + b)
    var = c**2 * a * b / ((a + b) ** 2 * (a + b + 1))
    assert t.mean().item() == pytest.approx(mean, abs=0.002)
    assert t.var().item() == pytest.approx(var, rel=0.02)
    assert mean < 0.5  # more mass near t = 0, the noise end
    assert t.min() >= 0.0 and t.max() <= c


@pytest.mark.parametrize("name", ["uniform", "mixed", "beta"])
def test_seeded_draws_repeat_and_differ_across_seeds(name):
    dist = make_timesteps(name)
    torch.testing.assert_close(draw(dist, 1000, seed=3), draw(dist, 1000, seed=3))
    assert not torch.equal(draw(dist, 1000, seed=3), draw(dist, 1000, seed=4))


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="p_uniform must lie in"):
        MixedLogitNormalTimesteps(p_uniform=1.5)
    with pytest.raises(ValueError, match="std must be positive"):
        MixedLogitNormalTimesteps(std=0.0)
    with pytest.raises(ValueError, match="Beta parameters must be positive"):
        BetaTimesteps(alpha=0.0)
    with pytest.raises(ValueError, match="cutoff must lie in"):
        BetaTimesteps(cutoff=1.5)
    with pytest.raises(ValueError, match="unknown timestep distribution 'normal'"):
        make_timesteps("normal")
