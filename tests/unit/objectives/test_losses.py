"""The four losses: objectives recomputed by hand, TorchRL loss conventions, masking, bad input."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from l1flow_rl import DiffusionLoss, FlowMatchingLoss, L1FlowActor, L1FlowLoss, RegressionLoss
from l1flow_rl.flow import (
    BetaTimesteps,
    DDIMSampler,
    DDPMSampler,
    DirectSampler,
    MixedLogitNormalTimesteps,
    TimestepDistribution,
    TwoStepSampler,
    VelocityEulerSampler,
    interpolate,
)

TO, H, D, A, B = 2, 16, 3, 2, 4

#: loss class -> (actor sampler, loss key)
LOSSES = {
    L1FlowLoss: (TwoStepSampler(0.5), "loss_l1flow"),
    FlowMatchingLoss: (VelocityEulerSampler(10), "loss_flow_matching"),
    DiffusionLoss: (DDPMSampler(), "loss_diffusion"),
    RegressionLoss: (DirectSampler(), "loss_regression"),
}
ALL = pytest.mark.parametrize("loss_cls", list(LOSSES), ids=lambda c: c.__name__)


def actor_for(loss_cls, **kwargs) -> L1FlowActor:
    return L1FlowActor.for_state(
        obs_dim=D,
        action_dim=A,
        obs_horizon=TO,
        pred_horizon=H,
        action_steps=8,
        down_dims=(16, 32),
        timestep_embed_dim=16,
        sampler=LOSSES[loss_cls][0],
        **kwargs,
    )


def batch(*dims: int, pad_from: int | None = None) -> TensorDict:
    dims = dims or (B,)
    td = TensorDict(
        {"observation": torch.randn(*dims, TO, D), "action_chunk": torch.rand(*dims, H, A) * 2 - 1},
        list(dims),
    )
    if pad_from is not None:
        is_pad = torch.zeros(*dims, H, dtype=torch.bool)
        is_pad[..., pad_from:] = True
        td["action_is_pad"] = is_pad
    return td


def seeded(loss_fn, td, seed=0):
    torch.manual_seed(seed)
    return loss_fn(td)


class FixedTimesteps(TimestepDistribution):
    def __init__(self, t: torch.Tensor) -> None:
        self.t = t

    def sample(self, n, *, device="cpu", generator=None):
        return self.t


# -- the objectives, recomputed by hand ---------------------------------------------------------------


@pytest.mark.parametrize(
    "loss_cls, error",
    [
        (L1FlowLoss, lambda pred, x0, x1: (pred - x1).abs()),  # L1 to the clean chunk
        (FlowMatchingLoss, lambda pred, x0, x1: (pred - (x1 - x0)).square()),  # MSE to the velocity
    ],
    ids=["l1flow", "flow_matching"],
)
def test_flow_objectives(loss_cls, error):
    actor = actor_for(loss_cls)
    t = torch.tensor([0.1, 0.4, 0.6, 0.9])
    td = batch()
    got = seeded(loss_cls(actor, timesteps=FixedTimesteps(t), reduction="none"), td)[LOSSES[loss_cls][1]]
    torch.manual_seed(0)
    x1 = td["action_chunk"]
    x0 = torch.randn_like(x1)
    p = actor.policy
    cond = p.encode(p.as_obs_dict(td["observation"]))
    torch.testing.assert_close(got, error(p.denoise(interpolate(x0, x1, t), t, cond), x0, x1))


def test_diffusion_objective_is_epsilon_mse_at_integer_steps():
    actor = actor_for(DiffusionLoss)
    loss_fn = DiffusionLoss(actor, reduction="none")
    td = batch()
    got = seeded(loss_fn, td)["loss_diffusion"]
    torch.manual_seed(0)  # the loss draws the steps, then the noise
    x1 = td["action_chunk"]
    steps = torch.randint(0, 100, (B,))
    noise = torch.randn_like(x1)
    p = actor.policy
    a = p.sampler.schedule.alphas_cumprod[steps].reshape(-1, 1, 1)
    x_k = a.sqrt() * x1 + (1 - a).sqrt() * noise
    cond = p.encode(p.as_obs_dict(td["observation"]))
    torch.testing.assert_close(got, (p.denoise(x_k, steps.float(), cond) - noise).square())


def test_regression_sees_a_zero_chunk_and_no_timestep():
    actor = actor_for(RegressionLoss)
    assert actor.policy.net.time_mlp is None
    td = batch()
    got = RegressionLoss(actor, reduction="none")(td)["loss_regression"]
    p = actor.policy
    pred = p.net(torch.zeros(B, H, A), None, p.encode(p.as_obs_dict(td["observation"])))
    torch.testing.assert_close(got, (pred - td["action_chunk"]).abs())
    mse = RegressionLoss(actor, loss_type="mse", reduction="none")(td)["loss_regression"]
    torch.testing.assert_close(mse, (pred - td["action_chunk"]).square())


def test_default_time_distributions_and_t_first_option():
    assert isinstance(L1FlowLoss(actor_for(L1FlowLoss)).timesteps, MixedLogitNormalTimesteps)
    assert isinstance(FlowMatchingLoss(actor_for(FlowMatchingLoss)).timesteps, BetaTimesteps)
    actor = actor_for(L1FlowLoss)
    L1FlowLoss(actor, t_first=0.3)
    assert isinstance(actor.sampler, TwoStepSampler) and actor.sampler.t_first == 0.3


def test_actions_are_normalised_before_the_loss():
    actor = actor_for(RegressionLoss)
    td = batch()
    reference = RegressionLoss(actor)(td)["loss_regression"]
    low, high = torch.tensor([0.0, -5.0]), torch.tensor([10.0, 5.0])
    actor.policy.action_normalizer.set_limits(low, high)
    env_units = td.clone()
    env_units["action_chunk"] = actor.policy.action_normalizer.unnormalize(td["action_chunk"])
    torch.testing.assert_close(RegressionLoss(actor)(env_units)["loss_regression"], reference)


# -- TorchRL conventions --------------------------------------------------------------------------


@ALL
def test_gradients_reach_every_parameter(loss_cls):
    actor = actor_for(loss_cls)
    out = loss_cls(actor)(batch())
    out[LOSSES[loss_cls][1]].backward()
    assert [n for n, p in actor.named_parameters() if p.grad is None] == []
    zero = [n for n, p in actor.named_parameters() if not p.grad.abs().sum() > 0]
    if loss_cls is RegressionLoss:  # the weights that multiply its all-zero input chunk get zero gradient
        assert zero == ["module.net.down.0.0.block1.0.weight", "module.net.down.0.0.residual.weight"]
    else:
        assert zero == []


@ALL
def test_output_keys_scalar_loss_and_detached_diagnostics(loss_cls):
    loss_fn = loss_cls(actor_for(loss_cls))
    out = loss_fn(batch())
    key = LOSSES[loss_cls][1]
    assert loss_fn.out_keys[0] == key and set(out.keys()) == set(loss_fn.out_keys)
    assert out[key].shape == () and out[key].requires_grad
    for name in loss_fn.out_keys[1:]:
        assert not out[name].requires_grad and torch.isfinite(out[name])
    assert loss_fn.in_keys == ["observation", "action_chunk", "action_is_pad"]


@ALL
def test_reductions(loss_cls):
    actor = actor_for(loss_cls)
    key = LOSSES[loss_cls][1]
    td = batch()
    per = {r: seeded(loss_cls(actor, reduction=r), td)[key] for r in ("mean", "sum", "none")}
    assert per["none"].shape == (B, H, A)
    torch.testing.assert_close(per["mean"], per["none"].mean())
    torch.testing.assert_close(per["sum"], per["none"].sum())
    with pytest.raises(ValueError, match="reduction must be 'mean', 'sum' or 'none'"):
        loss_cls(actor, reduction="max")


class StepwiseNet(torch.nn.Module):
    """Stands in for the UNet with a network that does not mix chunk steps, so a padded step's
    target can only reach the loss through that step's own error term."""

    def __init__(self, net) -> None:
        super().__init__()
        self.scale = torch.nn.Parameter(torch.full((net.action_dim,), 0.5))
        self.action_dim, self.global_cond_dim, self.timestep_embed_dim = (
            net.action_dim,
            net.global_cond_dim,
            0,
        )
        self.horizon_multiple, self.down_dims = 1, ()

    def forward(self, x, t, cond):
        time = 0.0 if t is None else t.reshape(-1, 1, 1)
        return x * self.scale + time + cond.mean(-1).reshape(-1, 1, 1)


@ALL
def test_padding_mask_removes_padded_steps(loss_cls):
    actor = actor_for(loss_cls)
    key = LOSSES[loss_cls][1]
    td = batch(pad_from=11)
    mean = seeded(loss_cls(actor, mask_padding=True), td)[key]
    none = seeded(loss_cls(actor, reduction="none", mask_padding=True), td)[key]
    assert (none[:, 11:] == 0).all() and (none[:, :11] > 0).any()
    torch.testing.assert_close(mean, none.sum() / (B * 11 * A))
    # No gradient flows back from the network's output at padded steps.
    outputs = []

    def keep_output(module, inputs, out):
        out.retain_grad()
        outputs.append(out)

    actor.policy.net.register_forward_hook(keep_output)
    seeded(loss_cls(actor, mask_padding=True), td)[key].backward()
    grad = outputs[-1].grad
    assert (grad[:, 11:] == 0).all() and (grad[:, :11] != 0).any()


@ALL
def test_changing_padded_targets_does_not_change_the_loss(loss_cls):
    # The generative losses feed the whole noised chunk to the network, padded steps included (as
    # at inference), so with the UNet a padded value can shift valid-step predictions; a step-wise
    # network isolates what the mask itself does.
    actor = actor_for(loss_cls)
    actor.policy.net = StepwiseNet(actor.policy.net)
    key = LOSSES[loss_cls][1]
    td = batch(pad_from=11)
    junk = td.clone()
    junk["action_chunk"][:, 11:] = 1e3
    masked = loss_cls(actor, mask_padding=True)
    out, out_junk = seeded(masked, td), seeded(masked, junk)
    torch.testing.assert_close(out_junk[key], out[key])
    for diagnostic in masked.out_keys[1:]:
        torch.testing.assert_close(out_junk[diagnostic], out[diagnostic])
    # by default (as Diffusion Policy and ManiSkill's baseline train) padded steps count
    assert seeded(loss_cls(actor), junk)[key] > 10 * out[key]


def test_regression_loss_ignores_padded_targets_with_the_real_network():
    actor = actor_for(RegressionLoss)  # its input is a zero chunk, so targets never reach the network
    td = batch(pad_from=5)
    junk = td.clone()
    junk["action_chunk"][:, 5:] = -1e3
    torch.testing.assert_close(
        RegressionLoss(actor, mask_padding=True)(junk)["loss_regression"],
        RegressionLoss(actor, mask_padding=True)(td)["loss_regression"],
    )


@ALL
def test_batch_dims_2x3_and_unbatched(loss_cls):
    actor = actor_for(loss_cls)
    key = LOSSES[loss_cls][1]
    assert loss_cls(actor, reduction="none")(batch(2, 3, pad_from=12))[key].shape == (2, 3, H, A)
    single = TensorDict({"observation": torch.randn(TO, D), "action_chunk": torch.rand(H, A)}, [])
    assert loss_cls(actor, reduction="none")(single)[key].shape == (H, A)
    assert loss_cls(actor)(single)[key].shape == ()


@ALL
def test_set_keys_plain_and_nested(loss_cls):
    actor = actor_for(loss_cls)
    loss_fn = loss_cls(actor)
    assert loss_fn.in_keys[0] == "observation"  # cached before set_keys
    loss_fn.set_keys(observation=("data", "obs"), action_chunk="act", action_is_pad=("data", "pad"))
    assert loss_fn.in_keys == [("data", "obs"), "act", ("data", "pad")]
    src = batch(pad_from=10)
    td = TensorDict(
        {
            "data": {"obs": src["observation"], "pad": src["action_is_pad"]},
            "act": src["action_chunk"],
        },
        [B],
    )
    key = LOSSES[loss_cls][1]
    expected = seeded(loss_cls(actor), src)[key]
    torch.testing.assert_close(seeded(loss_fn, td)[key], expected)
    with pytest.raises(KeyError, match=r"no 'act' entry .* Use set_keys"):
        loss_fn(src)
    loss_fn.set_keys(observation=None)  # back to the default
    assert loss_fn.tensor_keys.observation == "observation"


def test_float64_batches_are_accepted():
    actor = actor_for(L1FlowLoss)
    td = batch().apply(lambda x: x.double() if x.is_floating_point() else x)
    out = L1FlowLoss(actor)(td)["loss_l1flow"]
    assert out.dtype == torch.float32
    out.backward()


# -- wrong actor, bad input ----------------------------------------------------------------------


@pytest.mark.parametrize(
    "loss_cls, sampler, hint",
    [
        (L1FlowLoss, VelocityEulerSampler(10), "predicts 'sample'.*TwoStepSampler"),
        (FlowMatchingLoss, TwoStepSampler(0.5), "predicts 'velocity'.*VelocityEulerSampler"),
        (DiffusionLoss, TwoStepSampler(0.5), "predicts 'epsilon'.*DDPMSampler"),
        (DiffusionLoss, DirectSampler(), "predicts 'epsilon'"),
        (RegressionLoss, DDIMSampler(8), "predicts 'direct'.*DirectSampler"),
    ],
)
def test_loss_refuses_an_actor_built_for_another_method(loss_cls, sampler, hint):
    actor = L1FlowActor.for_state(obs_dim=D, action_dim=A, down_dims=(16, 32), sampler=sampler)
    with pytest.raises(ValueError, match=hint):
        loss_cls(actor)


def test_loss_refuses_a_foreign_module():
    module = TensorDictModule(torch.nn.Linear(3, 2), in_keys=["observation"], out_keys=["action_chunk"])
    with pytest.raises(TypeError, match="needs an L1FlowActor"):
        L1FlowLoss(module)


@pytest.fixture
def l1flow_loss():
    return L1FlowLoss(actor_for(L1FlowLoss))


def test_wrong_action_dim_or_horizon(l1flow_loss):
    td = batch()
    td2 = TensorDict({"observation": td["observation"], "action_chunk": torch.zeros(B, H, 3)}, [B])
    with pytest.raises(
        ValueError, match=r"'action_chunk' must have shape \[\*B, 16, 2\] .* got \(4, 16, 3\)"
    ):
        l1flow_loss(td2)
    td2 = TensorDict({"observation": td["observation"], "action_chunk": torch.zeros(B, 8, A)}, [B])
    with pytest.raises(ValueError, match=r"'action_chunk' must have shape \[\*B, 16, 2\] .* got \(4, 8, 2\)"):
        l1flow_loss(td2)
    td2 = TensorDict({"observation": torch.zeros(B, TO, 5), "action_chunk": td["action_chunk"]}, [B])
    with pytest.raises(ValueError, match=r"'observation' must have shape \[\*B, 2, 3\] .* got \(4, 2, 5\)"):
        l1flow_loss(td2)


def test_missing_keys(l1flow_loss):
    td = batch()
    with pytest.raises(KeyError, match=r"no 'action_chunk' entry \(the demonstrated chunk, \[\*B, 16, 2\]\)"):
        l1flow_loss(td.exclude("action_chunk"))
    with pytest.raises(
        KeyError, match=r"no 'observation' entry \(the observation history, \[\*B, 2, \.\.\.\]\)"
    ):
        l1flow_loss(td.exclude("observation"))


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_batches(l1flow_loss, bad):
    td = batch()
    td["action_chunk"][2, 5, 1] = bad
    with pytest.raises(ValueError, match=r"'action_chunk' contains NaN or Inf \(flat batch rows \[2\]\)"):
        l1flow_loss(td)
    td = batch()
    td["observation"][1, 0, 0] = bad
    with pytest.raises(ValueError, match="'observation' contains NaN or Inf"):
        l1flow_loss(td)


def test_mismatched_batches_and_pad_mask(l1flow_loss):
    td = TensorDict({"observation": torch.randn(3, TO, D), "action_chunk": torch.zeros(3, H, A)}, [3])
    td2 = TensorDict({"observation": torch.randn(2, 3, TO, D), "action_chunk": torch.zeros(6, H, A)}, [])
    with pytest.raises(
        ValueError, match=r"'observation' has batch dims \[2, 3\] but 'action_chunk' has \[6\]"
    ):
        l1flow_loss(td2)
    td["action_is_pad"] = torch.zeros(3, H - 1, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"'action_is_pad' must have shape \[3, 16\], got \(3, 15\)"):
        l1flow_loss(td)
