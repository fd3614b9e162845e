"""Normalisers (limits, Gaussian, degenerate ranges, state_dict round trip) and the EMA helper."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from l1flow_rl import L1FlowActor, Normalizer, NormalizerDict, dp_ema_decay, make_ema


def test_limits_maps_the_data_range_to_minus_one_one_and_back():
    data = torch.stack([torch.linspace(-3.0, 5.0, 50), torch.linspace(100.0, 101.0, 50)], -1)
    norm = Normalizer(2).fit(data, "limits")
    y = norm.normalize(data)
    torch.testing.assert_close(y.min(0).values, torch.tensor([-1.0, -1.0]))
    torch.testing.assert_close(y.max(0).values, torch.tensor([1.0, 1.0]))
    torch.testing.assert_close(norm.unnormalize(y), data, rtol=1e-5, atol=1e-4)
    assert norm.mode == "limits"


def test_limits_shifts_degenerate_dimensions_so_constants_map_to_zero():
    data = torch.stack([torch.linspace(0.0, 1.0, 20), torch.full((20,), 7.5)], -1)
    norm = Normalizer(2).fit(data, "limits")
    y = norm.normalize(data)
    assert (y[:, 1] == 0).all()
    torch.testing.assert_close(norm.unnormalize(y), data)
    # a range below range_eps is shifted, not stretched
    tiny = torch.tensor([[1.0, 2.0], [1.0 + 5e-5, 3.0]])
    torch.testing.assert_close(
        Normalizer(2).fit(tiny, "limits").normalize(tiny)[:, 0], torch.tensor([0.0, 5e-5])
    )


def test_gaussian_standardises_and_round_trips():
    data = (
        torch.randn(1000, 3, generator=torch.Generator().manual_seed(0)) * torch.tensor([2.0, 0.1, 5.0]) + 4
    )
    data[:, 2] = -1.0  # constant dimension: only shifted
    norm = Normalizer(3).fit(data, "gaussian")
    y = norm.normalize(data)
    torch.testing.assert_close(y.mean(0), torch.zeros(3), atol=1e-5, rtol=0)
    torch.testing.assert_close(y[:, :2].std(0, correction=0), torch.ones(2), atol=1e-5, rtol=0)
    assert (y[:, 2] == 0).all()
    torch.testing.assert_close(norm.unnormalize(y), data, rtol=1e-5, atol=1e-5)


def test_identity_before_fit_and_after_fitting_identity():
    x = torch.randn(5, 2)
    torch.testing.assert_close(Normalizer(2).normalize(x), x)
    norm = Normalizer(2).fit(x * 10, "limits").fit(x, "identity")
    torch.testing.assert_close(norm.normalize(x), x)


def test_normalizer_fit_errors_name_the_data():
    with pytest.raises(
        ValueError, match=r"normaliser for 'action' expects trailing shape \(2,\), got \(5, 3\)"
    ):
        Normalizer(2).fit(torch.zeros(5, 3), name="action")
    with pytest.raises(
        ValueError, match="cannot fit the normaliser for 'action': the data contain NaN or Inf"
    ):
        Normalizer(2).fit(torch.tensor([[0.0, float("nan")]]), name="action")
    with pytest.raises(ValueError, match="must be one of"):
        Normalizer(2).fit(torch.zeros(5, 2), "minmax")
    with pytest.raises(ValueError, match="zero samples"):
        Normalizer(2).fit(torch.zeros(0, 2))
    with pytest.raises(KeyError, match="entry 'goal' is missing"):
        NormalizerDict({"qpos": (3,), "goal": (2,)}).fit({"qpos": torch.zeros(4, 3)})


def _actor(**kw) -> L1FlowActor:
    return L1FlowActor.for_state(obs_dim=3, action_dim=2, down_dims=(16, 32), timestep_embed_dim=16, **kw)


def test_fitted_actor_state_dict_round_trip_acts_in_environment_units():
    torch.manual_seed(0)
    actor = _actor()
    obs = torch.randn(200, 2, 3) * 4 + 10
    actions = torch.rand(200, 16, 2) * torch.tensor([0.5, 30.0]) + torch.tensor([2.0, -10.0])
    actor.policy.fit_normalizers(observation=obs, action=actions, mode="limits")
    fresh = _actor()
    fresh.load_state_dict(actor.state_dict())
    assert fresh.policy.action_normalizer.mode == "limits"
    td = TensorDict({"observation": obs[:4]}, [4])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        a, b = actor(td.clone())["action_chunk"], fresh(td.clone())["action_chunk"]
    torch.testing.assert_close(a, b)
    # the network's output in [-1, 1] lands in the demonstrated range, in environment units
    with torch.no_grad():
        x1 = fresh.policy.action_normalizer.unnormalize(torch.tensor([[-1.0, -1.0], [1.0, 1.0]]))
    torch.testing.assert_close(
        x1, torch.stack([actions.amin((0, 1)), actions.amax((0, 1))]), rtol=1e-5, atol=1e-4
    )


def test_observation_normaliser_is_applied_before_encoding():
    actor = _actor()
    obs = torch.randn(50, 2, 3) * 3 + 7
    actor.policy.fit_normalizers(observation=obs, mode="gaussian")
    flat = actor.policy.as_obs_dict(obs)
    feats = actor.policy.encode(flat).reshape(50, 2, 3)
    assert feats.mean().abs() < 0.1 and (feats.std() - 1).abs() < 0.1


# -- EMA --------------------------------------------------------------------------------------------


def test_dp_ema_decay_schedule():
    assert dp_ema_decay(0) == 0.0
    assert dp_ema_decay(1) == pytest.approx(1 - 2**-0.75)
    assert dp_ema_decay(10) == pytest.approx(1 - 11**-0.75)
    assert dp_ema_decay(10**9) == 0.9999
    values = [dp_ema_decay(s) for s in range(0, 5000, 50)]
    assert values == sorted(values)


class _DiffusionPolicyEMA:
    """Diffusion Policy's EMAModel schedule, written out here independently of ``l1flow_rl.modules.ema``: the
    k-th call (k = 0, 1, ...) blends with decay(max(0, k - update_after_step - 1)), where
    decay(s) = 0 for s <= 0, else clamp(1 - (1 + s / inv_gamma) ** -power, min_value, max_value)."""

    def __init__(self, params, power=0.75, inv_gamma=1.0, max_value=0.9999, update_after_step=0):
        self.params = [p.detach().clone() for p in params]
        self.power, self.inv_gamma, self.max_value = power, inv_gamma, max_value
        self.update_after_step, self.optimization_step = update_after_step, 0

    def decay(self) -> float:
        s = max(0, self.optimization_step - self.update_after_step - 1)
        if s <= 0:
            return 0.0
        return max(0.0, min(1 - (1 + s / self.inv_gamma) ** -self.power, self.max_value))

    def step(self, params) -> None:
        d = self.decay()
        self.params = [d * mine + (1 - d) * p.detach() for mine, p in zip(self.params, params)]
        self.optimization_step += 1


@pytest.mark.parametrize(("power", "max_decay"), [(0.75, 0.9999), (2 / 3, 0.6)])
def test_ema_follows_diffusion_policys_schedule(power, max_decay):
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Linear(4, 2))
    ema = make_ema(model, power=power, max_decay=max_decay)
    reference = _DiffusionPolicyEMA(model.parameters(), power=power, max_value=max_decay)
    for _ in range(12):  # with max_decay=0.6 and power 2/3 the clamp binds from the 5th update on
        with torch.no_grad():
            for p in model.parameters():
                p.add_(torch.randn_like(p))
        ema.update_parameters(model)
        reference.step(model.parameters())
        for mine, theirs in zip(ema.module.parameters(), reference.params):
            torch.testing.assert_close(mine, theirs, rtol=1e-6, atol=1e-6)
    # From the third update on the average lags the live weights.
    assert not torch.allclose(ema.module[0].weight, model[0].weight)


def test_ema_copies_buffers_such_as_normalisers():
    actor = _actor()
    ema = make_ema(actor)
    actor.policy.fit_normalizers(action=torch.rand(10, 16, 2) * 5, mode="limits")  # after the copy was made
    for _ in range(3):
        ema.update_parameters(actor)
    averaged = ema.module.policy.action_normalizer
    torch.testing.assert_close(averaged.scale, actor.policy.action_normalizer.scale)
    assert averaged.mode_id.dtype == torch.long and averaged.mode == "limits"
    assert math.isclose(float(averaged.offset[0]), float(actor.policy.action_normalizer.offset[0]))


def test_ema_decay_is_read_on_the_host_and_its_counter_stays_on_the_cpu():
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Linear(4, 2))
    ema = make_ema(model)
    reference = _DiffusionPolicyEMA(model.parameters())
    decays = []
    for _ in range(5):
        decays.append(ema.decay())
        ema.update_parameters(model)
    reference.optimization_step = 0
    expected = []
    for _ in range(5):
        expected.append(reference.decay())
        reference.optimization_step += 1
    assert decays == expected and decays[:2] == [0.0, 0.0] and decays[2] == pytest.approx(1 - 2**-0.75)
    # Moving or casting the EMA leaves its step counter a CPU integer (the host reads it each update).
    ema.to(torch.float64)
    model.to(torch.float64)
    assert ema.module[0].weight.dtype == torch.float64
    assert ema.n_averaged.device.type == "cpu" and ema.n_averaged.dtype == torch.long
    ema.update_parameters(model)
    assert int(ema.n_averaged) == 6
    # The counter travels in the state_dict and sets the next decay after loading.
    fresh = make_ema(model)
    fresh.load_state_dict(ema.state_dict())
    assert fresh.decay() == ema.decay() == pytest.approx(dp_ema_decay(5))
    with pytest.raises(ValueError, match="holds 4 parameters but the model passed has 2"):
        ema.update_parameters(torch.nn.Linear(3, 4).double())
