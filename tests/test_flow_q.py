"""FlowQLoss: TorchRL key conformance, reductions, where gradients go, the chunked TD target by hand,
gradients through both L1 Flow evaluations in direct mode; the critic and the one-step actor."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.objectives import SoftUpdate

from l1flow_rl import FlowQLoss, L1FlowActor
from l1flow_rl.networks.critic import ChunkCritic, chunk_critic_module
from l1flow_rl.networks.one_step import make_one_step_actor

# the tests build losses without a SoftUpdate; TorchRL warns about that on every target access
pytestmark = pytest.mark.filterwarnings("ignore:No target network updater")

TO, H, K, D, A = 2, 8, 4, 3, 2
B = 6


def tiny_actor() -> L1FlowActor:
    return L1FlowActor.for_state(
        obs_dim=D,
        action_dim=A,
        obs_horizon=TO,
        pred_horizon=H,
        action_steps=K,
        down_dims=(8, 16),
        timestep_embed_dim=8,
    )


def critics(actor: L1FlowActor, n: int = 2, h: int = K) -> list:
    return [
        chunk_critic_module(ChunkCritic.from_policy(actor, action_horizon=h, hidden_dims=(16, 16)))
        for _ in range(n)
    ]


def batch(b: int = B, *, valid=None, reward=None, done=None, terminated=None) -> TensorDict:
    ones = torch.ones(b, 1, dtype=torch.bool)
    return TensorDict(
        {
            "observation": torch.randn(b, TO, D),
            "action_chunk": torch.rand(b, H, A) * 2 - 1,
            "action_is_pad": torch.zeros(b, H, dtype=torch.bool),
            "chunk_valid": ones if valid is None else valid,
            "next": {
                "observation": torch.randn(b, TO, D),
                "reward": torch.rand(b, 1) if reward is None else reward,
                "done": ~ones if done is None else done,
                "terminated": ~ones if terminated is None else terminated,
            },
        },
        batch_size=[b],
    )


def distill_loss(**kwargs) -> tuple[FlowQLoss, L1FlowActor, L1FlowActor]:
    teacher = tiny_actor()
    mu = make_one_step_actor(teacher)
    loss = FlowQLoss(mu, critics(teacher), teacher_network=teacher, **kwargs)
    return loss, mu, teacher


def grads(params) -> list[torch.Tensor | None]:
    return [p.grad for p in params]


def test_one_step_actor_is_the_teacher_network_read_at_t0():
    teacher = tiny_actor()
    mu = make_one_step_actor(teacher)
    assert mu.sampler.nfe == 1 and teacher.sampler.nfe == 2
    assert not {id(p) for p in mu.parameters()} & {id(p) for p in teacher.parameters()}
    obs = torch.randn(5, TO, D)
    z = torch.randn(5, H, A)
    with torch.no_grad():
        cond = teacher.policy.encode(teacher.policy.as_obs_dict(obs))
        expected = teacher.policy.denoise(z, torch.zeros(5), cond)  # f(z, 0 | s)
        got = mu.policy.sampler(
            lambda x, t: mu.policy.denoise(x, t, mu.policy.encode(mu.policy.as_obs_dict(obs))), z
        )
    torch.testing.assert_close(got, expected)
    scratch = make_one_step_actor(teacher, init="scratch")
    assert not torch.equal(scratch.policy.net.head[-1].weight, teacher.policy.net.head[-1].weight)
    with pytest.raises(ValueError, match="init"):
        make_one_step_actor(teacher, init="zeros")


def test_critic_shapes_normalisers_and_independent_members():
    actor = tiny_actor()
    actor.policy.action_normalizer.set_limits(torch.tensor([-2.0, 0.0]), torch.tensor([2.0, 4.0]))
    critic = ChunkCritic.from_policy(actor, action_horizon=3, hidden_dims=(16,))
    torch.testing.assert_close(critic.action_normalizer.scale, actor.policy.action_normalizer.scale)
    assert critic(torch.randn(2, 5, TO, D), torch.randn(2, 5, 3, A)).shape == (2, 5, 1)
    assert [m for m in critic.mlp if isinstance(m, torch.nn.LayerNorm)]
    with pytest.raises(ValueError, match=r"action chunk must have shape \[4, 3, 2\]"):
        critic(torch.randn(4, TO, D), torch.randn(4, K, A))
    with pytest.raises(ValueError, match="observation entry 'state'"):
        critic(torch.randn(4, TO + 1, D), torch.randn(4, 3, A))
    loss, *_ = distill_loss()
    q = loss._q(
        loss.policy.as_obs_dict(torch.randn(B, TO, D)), torch.rand(B, K, A), loss.qvalue_network_params
    )
    assert q.shape == (2, B, 1) and not torch.allclose(q[0], q[1])  # two independently initialised critics


def test_set_keys_with_nested_keys_and_in_keys():
    loss, *_ = distill_loss(alpha=3.0)
    keys = {
        "observation": ("agent", "obs"),
        "action_chunk": ("agent", "chunk"),
        "action_is_pad": ("agent", "pad"),
        "reward": ("agent", "ret"),
        "done": ("agent", "done"),
        "terminated": ("agent", "term"),
        "next_observation": ("next", "agent", "obs"),
        "chunk_valid": ("agent", "valid"),
    }
    loss.set_keys(**keys)
    assert ("next", "agent", "ret") in loss.in_keys and ("agent", "valid") in loss.in_keys
    assert loss.bc_loss_module.tensor_keys.observation == ("agent", "obs")
    assert loss.value_estimator.tensor_keys.reward == ("agent", "ret")
    src = batch()
    td = TensorDict(
        {
            "agent": {
                "obs": src["observation"],
                "chunk": src["action_chunk"],
                "pad": src["action_is_pad"],
                "valid": src["chunk_valid"],
            },
            "next": {
                "agent": {
                    "obs": src["next", "observation"],
                    "ret": src["next", "reward"],
                    "done": src["next", "done"],
                    "term": src["next", "terminated"],
                }
            },
        },
        batch_size=[B],
    )
    out = loss(td)
    assert set(out.keys()) == set(loss.out_keys)
    assert out["loss_actor"].requires_grad and out["loss_qvalue"].requires_grad
    for key in loss.diagnostic_keys:
        assert not out[key].requires_grad
    with pytest.raises(KeyError, match=r"agent.*chunk"):
        loss(batch())  # the default keys are gone
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(observations="x")


def test_reductions_agree_and_invalid_chunks_are_zero():
    torch.manual_seed(0)
    valid = torch.tensor([True, True, False, True, False, True]).unsqueeze(-1)
    td = batch(valid=valid)
    out, ref_state = {}, None
    for reduction in ("none", "mean", "sum"):
        loss, *_ = distill_loss(reduction=reduction)
        if ref_state is None:
            ref_state = loss.state_dict()
        loss.load_state_dict(ref_state)  # the same networks under each reduction
        torch.manual_seed(1)
        out[reduction] = loss(td.clone())
    none_q, none_a = out["none"]["loss_qvalue"], out["none"]["loss_actor"]
    assert none_q.shape == (B,) and none_a.shape == (B,)
    assert (none_q[~valid.squeeze(-1)] == 0).all() and (none_q[valid.squeeze(-1)] > 0).all()
    torch.testing.assert_close(out["sum"]["loss_qvalue"], none_q.sum())
    torch.testing.assert_close(out["mean"]["loss_qvalue"], none_q.sum() / valid.sum())
    torch.testing.assert_close(out["mean"]["loss_actor"], none_a.mean())
    torch.testing.assert_close(out["mean"]["valid_fraction"], torch.tensor(4 / 6))


def test_batch_dims_beyond_one():
    loss, *_ = distill_loss(reduction="none")
    td = batch(6).reshape(2, 3)
    out = loss(td)
    assert out["loss_qvalue"].shape == (2, 3) and out["loss_actor"].shape == (2, 3)


@pytest.mark.parametrize("train_teacher", [False, True], ids=["frozen", "co-trained"])
def test_distill_gradients_reach_only_the_intended_parameters(train_teacher):
    loss, mu, teacher = distill_loss(alpha=10.0, train_teacher=train_teacher)
    td = batch()
    loss_a, _ = loss.actor_loss(td)
    loss_a.backward()
    assert all(g is not None and g.abs().sum() > 0 for g in grads(mu.policy.net.parameters()))
    assert all(p.grad is None for p in loss.qvalue_network_params.values(True, True))
    teacher_grads = grads(teacher.parameters())
    if train_teacher:
        assert sum(g is not None and g.abs().sum() > 0 for g in teacher_grads) > len(teacher_grads) // 2
    else:
        assert all(g is None for g in teacher_grads) and not any(
            p.requires_grad for p in teacher.parameters()
        )
    for p in mu.parameters():
        p.grad = None
    for p in teacher.parameters():
        p.grad = None
    loss_q, _ = loss.qvalue_loss(td)
    loss_q.backward()
    q_grads = [p.grad for p in loss.qvalue_network_params.values(True, True) if p.requires_grad]
    assert q_grads and all(g is not None for g in q_grads)
    assert all(p.grad is None for p in mu.parameters()) and all(p.grad is None for p in teacher.parameters())
    assert all(not p.requires_grad for p in loss.target_qvalue_network_params.values(True, True))


def test_direct_mode_gradient_flows_through_both_sampler_evaluations():
    actor = tiny_actor()
    loss = FlowQLoss(actor, critics(actor), mode="direct", alpha=0.0)  # only the Q term: no BC pass
    outputs: list[torch.Tensor] = []
    reached: list[bool] = []

    def keep(module, args, output):
        if output.requires_grad:
            outputs.append(output)
            output.register_hook(lambda g: reached.append(bool(g.abs().sum() > 0)))

    handle = actor.policy.net.register_forward_hook(keep)
    loss_a, _ = loss.actor_loss(batch())
    handle.remove()
    assert len(outputs) == 2  # the two L1 Flow network evaluations, both in the graph
    loss_a.backward()
    assert reached == [True, True]
    assert actor.policy.net.head[-1].weight.grad.abs().sum() > 0


def test_direct_mode_bc_term_is_the_l1flow_loss():
    actor = tiny_actor()
    loss = FlowQLoss(actor, critics(actor), mode="direct", alpha=2.5, normalize_q_loss=False)
    for p in loss.qvalue_network_params.values(True, True):  # Q == 0 everywhere: only BC remains
        p.data.zero_()
    td = batch()
    torch.manual_seed(3)
    loss_a, meta = loss.actor_loss(td)
    from l1flow_rl import L1FlowLoss

    torch.manual_seed(3)
    _ = torch.randn(B, H, A)  # the actor's noise is drawn first
    with torch.no_grad():
        cond = actor.policy.encode(actor.policy.as_obs_dict(td["observation"]))
        actor.policy.sampler(lambda x, t: actor.policy.denoise(x, t, cond), _)
    bc = L1FlowLoss(actor)(td)["loss_l1flow"]
    torch.testing.assert_close(loss_a, 2.5 * bc)
    torch.testing.assert_close(meta["bc_loss"], bc.detach())
    assert meta["q_mean"] == 0 and torch.isnan(meta["distill_loss"])


def constant_critics(actor, biases, h):
    nets = critics(actor, len(biases), h)
    for net, b in zip(nets, biases):
        head = net.module.mlp[-1]
        head.weight.data.zero_()
        head.bias.data.fill_(b)
    return nets


@pytest.mark.parametrize("q_agg", ["mean", "min"])
def test_chunked_td_target_by_hand(q_agg):
    """One episode, rewards 1..5, terminated after step 4 (L = 5), h = 3, gamma = 0.9; the
    windows at t = 0 (inside), t = 2 (ends exactly at the episode's end) and t = 3 (runs past it)."""
    gamma, h, biases = 0.9, 3, (2.0, 4.0)
    teacher = tiny_actor()
    loss = FlowQLoss(
        make_one_step_actor(teacher),
        constant_critics(teacher, biases, h),
        teacher_network=teacher,
        gamma=gamma,
        rl_horizon=h,
        q_agg=q_agg,
        reduction="none",
    )
    r = [1.0, 2.0, 3.0, 4.0, 5.0]
    ret = [sum(gamma**i * r[t + i] for i in range(min(h, 5 - t))) for t in (0, 2, 3)]
    assert ret == pytest.approx([5.23, 10.65, 8.5])
    done = torch.tensor([[False], [True], [True]])
    td = batch(
        3,
        reward=torch.tensor(ret).unsqueeze(-1),
        done=done,
        terminated=done,
        valid=torch.tensor([[True], [True], [False]]),
    )
    q_next = min(biases) if q_agg == "min" else sum(biases) / 2
    target = torch.tensor([5.23 + gamma**3 * q_next, 10.65, float("nan")])
    out, meta = loss.qvalue_loss(td)
    expected = sum((b - target) ** 2 for b in biases)
    torch.testing.assert_close(out[:2], expected[:2].float())
    assert out[2] == 0  # the chunk that crosses the episode's end drops out
    torch.testing.assert_close(meta["target_mean"], target[:2].mean().float())
    # a truncated (not terminated) end bootstraps from Q(s_{t+h}), discounted by gamma ** h
    td["next", "terminated"] = torch.zeros(3, 1, dtype=torch.bool)
    out, _ = loss.qvalue_loss(td)
    t2 = 10.65 + gamma**3 * q_next
    torch.testing.assert_close(out[1], torch.tensor(sum((b - t2) ** 2 for b in biases)).float())


def test_normalize_q_loss_lambda_is_one_over_mean_abs_q():
    teacher = tiny_actor()
    for normalize, expected_loss in ((True, -1.0), (False, -3.0)):
        loss = FlowQLoss(
            make_one_step_actor(teacher),
            constant_critics(teacher, (2.0, 4.0), K),
            teacher_network=teacher,
            alpha=0.0,
            normalize_q_loss=normalize,
        )
        loss_a, meta = loss.actor_loss(batch())
        torch.testing.assert_close(loss_a, torch.tensor(expected_loss))
        torch.testing.assert_close(meta["lambda"], torch.tensor(1 / 3.0 if normalize else 1.0))
        torch.testing.assert_close(meta["q_mean"], torch.tensor(3.0))


def test_distillation_target_is_the_clipped_teacher_chunk_from_the_same_noise():
    loss, mu, teacher = distill_loss(alpha=1.0)
    with torch.no_grad():  # push the teacher far outside [-1, 1] so clipping shows
        teacher.policy.net.head[-1].bias.fill_(5.0)
    td = batch()
    torch.manual_seed(7)
    _, meta = loss.actor_loss(td)
    torch.manual_seed(7)
    z = torch.randn(B, H, A)
    with torch.no_grad():
        obs = mu.policy.as_obs_dict(td["observation"])
        x_mu = loss._sample(mu.policy, obs, z)
        x_t = loss._sample(teacher.policy, obs, z)
    assert x_t.max() > 1.5
    torch.testing.assert_close(meta["distill_loss"], (x_mu - x_t.clamp(-1, 1)).square().mean())


def test_soft_update_moves_targets_towards_the_critics():
    loss, *_ = distill_loss()
    updater = SoftUpdate(loss, tau=0.5)
    key = ("module", "mlp", "0", "weight")
    before = loss.target_qvalue_network_params.get(key).clone()
    torch.testing.assert_close(before, loss.qvalue_network_params.get(key).data)
    loss.qvalue_network_params.get(key).data.add_(1.0)
    updater.step()
    torch.testing.assert_close(loss.target_qvalue_network_params.get(key), before + 0.5)


def test_bad_construction_and_input_are_named():
    teacher = tiny_actor()
    with pytest.raises(ValueError, match="needs teacher_network"):
        FlowQLoss(make_one_step_actor(teacher), critics(teacher))
    with pytest.raises(ValueError, match="teacher_network must be None"):
        FlowQLoss(teacher, critics(teacher), mode="direct", teacher_network=tiny_actor())
    with pytest.raises(ValueError, match="share parameters"):
        FlowQLoss(teacher, critics(teacher), teacher_network=teacher)
    with pytest.raises(ValueError, match="rl_horizon=8"):
        FlowQLoss(teacher, critics(teacher), mode="direct", rl_horizon=8)
    with pytest.raises(ValueError, match="q_agg"):
        FlowQLoss(teacher, critics(teacher), mode="direct", q_agg="max")
    with pytest.raises(ValueError, match="got 3 critics"):
        FlowQLoss(teacher, critics(teacher, 3), mode="direct")
    loss = FlowQLoss(teacher, critics(teacher), mode="direct")
    td = batch()
    td["chunk_valid"] = torch.ones(B, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"'chunk_valid' must have shape \[6, 1\]"):
        loss.qvalue_loss(td)
    with pytest.raises(KeyError, match=r"next.*reward.*the discounted chunk return"):
        loss.qvalue_loss(batch().exclude(("next", "reward")))
    with pytest.raises(ValueError, match="action_chunk"):
        loss.actor_loss(batch().set("action_chunk", torch.zeros(B, H + 1, A)))


def test_best_of_n_target_is_the_max_over_draws_and_no_actor_is_trained():
    """The TD target backs up the best of N drawn next chunks under the target critics (by hand);
    draw 0 uses the noise a single draw would, so N = 1 is the direct mode's target and N = 8's is
    higher; the actor gets no loss and no gradient."""
    torch.manual_seed(0)
    actor, nets, gamma, n, b = tiny_actor(), critics(tiny_actor(), 2), 0.9, 8, 32
    td = batch(b)

    def target_mean(mode: str, draws: int) -> torch.Tensor:
        loss = FlowQLoss(actor, nets, mode=mode, num_samples=draws, gamma=gamma)
        torch.manual_seed(1)
        return loss.qvalue_loss(td)[1]["target_mean"]

    loss = FlowQLoss(actor, nets, mode="best_of_n", num_samples=n, gamma=gamma)
    policy = actor.policy
    torch.manual_seed(1)
    with torch.no_grad():
        next_obs = policy.as_obs_dict(td["next", "observation"])
        noise = torch.randn(n * b, H, A)
        x = loss._clip(loss._sample(policy, torch.cat([next_obs] * n), noise), policy)
        chunk = policy.action_normalizer.unnormalize(loss._executed(x))
        q = loss._q(torch.cat([next_obs] * n), chunk, loss.target_qvalue_network_params).mean(0)
        best = q.reshape(n, b).max(0).values  # draw j of sample i is row j * b + i
    expected = (td["next", "reward"].reshape(b) + gamma**K * best).mean()
    torch.testing.assert_close(target_mean("best_of_n", n), expected)
    torch.testing.assert_close(target_mean("best_of_n", 1), target_mean("direct", 1))
    assert target_mean("best_of_n", n) > target_mean("best_of_n", 1)

    assert not any(p.requires_grad for p in loss.actor_network_params.values(True, True))
    out = loss(td)
    assert out["loss_actor"] == 0 and not out["loss_actor"].requires_grad
    assert torch.isnan(out["distill_loss"]) and torch.isfinite(out["q_mean"])
    out["loss_qvalue"].backward()
    trained = [p for p in loss.qvalue_network_params.values(True, True) if p.requires_grad]
    assert trained and all(p.grad is not None for p in trained)
    with pytest.raises(ValueError, match="num_samples must be >= 1"):
        FlowQLoss(actor, nets, mode="best_of_n", num_samples=0)


def test_mean_backup_is_the_average_over_draws_of_the_policy():
    """backup="mean" values the next state as the mean over the drawn chunks' target values (by
    hand); backup_samples sets the number of draws in any mode, and one draw of either backup is the
    direct mode's target; bad values are refused."""
    torch.manual_seed(0)
    actor, nets, gamma, n, b = tiny_actor(), critics(tiny_actor(), 2), 0.9, 6, 16
    td = batch(b)

    def target(**kwargs) -> torch.Tensor:
        loss = FlowQLoss(actor, nets, gamma=gamma, **kwargs)
        torch.manual_seed(1)
        return loss.qvalue_loss(td)[1]["target_mean"]

    loss = FlowQLoss(actor, nets, mode="best_of_n", num_samples=n, backup="mean", gamma=gamma)
    assert loss.backup_samples == n
    policy = actor.policy
    torch.manual_seed(1)
    with torch.no_grad():
        next_obs = torch.cat([policy.as_obs_dict(td["next", "observation"])] * n)
        x = loss._clip(loss._sample(policy, next_obs, torch.randn(n * b, H, A)), policy)
        chunk = policy.action_normalizer.unnormalize(loss._executed(x))
        q = loss._q(next_obs, chunk, loss.target_qvalue_network_params).mean(0).reshape(n, b)
    mean_target = (td["next", "reward"].reshape(b) + gamma**K * q.mean(0)).mean()
    max_target = (td["next", "reward"].reshape(b) + gamma**K * q.max(0).values).mean()
    torch.testing.assert_close(target(mode="best_of_n", num_samples=n, backup="mean"), mean_target)
    torch.testing.assert_close(target(mode="direct", backup="mean", backup_samples=n), mean_target)
    torch.testing.assert_close(target(mode="direct", backup_samples=n), max_target)
    assert mean_target < max_target
    one = target(mode="direct")
    torch.testing.assert_close(target(mode="best_of_n", num_samples=n, backup="mean", backup_samples=1), one)
    torch.testing.assert_close(target(mode="best_of_n", num_samples=n, backup_samples=1), one)
    # one_step: the network read once at t = 0 from the same noise (one draw unless told otherwise)
    loss = FlowQLoss(actor, nets, mode="best_of_n", num_samples=n, backup="one_step", gamma=gamma)
    assert loss.backup_samples == 1
    torch.manual_seed(1)
    next_obs, chunk = _one_step_next_chunk(loss, td)
    with torch.no_grad():
        q = loss._q(next_obs, chunk, loss.target_qvalue_network_params).mean(0).reshape(b)
    one_step_target = (td["next", "reward"].reshape(b) + gamma**K * q).mean()
    torch.testing.assert_close(target(mode="best_of_n", num_samples=n, backup="one_step"), one_step_target)
    assert not torch.allclose(one_step_target, one)  # not the two-step chunk
    with pytest.raises(ValueError, match="backup must be one of"):
        FlowQLoss(actor, nets, mode="direct", backup="min")
    with pytest.raises(ValueError, match="backup_samples must be >= 1"):
        FlowQLoss(actor, nets, mode="direct", backup_samples=0)


@pytest.mark.parametrize(
    "name",
    [
        "l1flow_rl.objectives.flow_q",
        "l1flow_rl.networks.critic",
        "l1flow_rl.networks.one_step",
        "l1flow_rl.networks.best_of_n",
    ],
)
def test_docstring_examples_run(name):
    import doctest
    import importlib

    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0


@torch.no_grad()
def _one_step_next_chunk(loss, td):
    """(next observation dict, the one-step chunk f(z, 0 | s') in env units, executed steps), by hand."""
    policy = loss.policy
    next_obs = policy.as_obs_dict(td["next", "observation"])
    b = next_obs.shape[0]
    x = policy.denoise(torch.randn(b, H, A), torch.zeros(b), policy.encode(next_obs)).clamp(-1, 1)
    return next_obs, policy.action_normalizer.unnormalize(loss._executed(x))


def test_residual_critic_input_in_the_td_target_and_only_for_best_of_n():
    """With critic_input="residual" the TD target values the next chunk minus the frozen policy's
    zero-noise chunk at the next state (by hand), and the data chunk's Q reads its own residual."""
    torch.manual_seed(0)
    actor, nets, gamma, b = tiny_actor(), critics(tiny_actor(), 2), 0.9, 16
    td = batch(b)
    loss = FlowQLoss(
        actor, nets, mode="best_of_n", num_samples=4, backup="one_step", gamma=gamma, critic_input="residual"
    )
    torch.manual_seed(1)
    next_obs, chunk = _one_step_next_chunk(loss, td)
    with torch.no_grad():
        own = actor.policy(td["next", "observation"], deterministic=True)[:, :K]
        loss.critic_input = "action"  # the critics on the residual, by hand
        q = loss._q(next_obs, chunk - own, loss.target_qvalue_network_params).mean(0).reshape(b)
        loss.critic_input = "residual"
    expected = (td["next", "reward"].reshape(b) + gamma**K * q).mean()
    torch.manual_seed(1)
    torch.testing.assert_close(loss.qvalue_loss(td)[1]["target_mean"], expected)
    for mode in ("direct", "distill"):
        with pytest.raises(ValueError, match="critic_input='residual' needs mode='best_of_n'"):
            kwargs = {"teacher_network": tiny_actor()} if mode == "distill" else {}
            FlowQLoss(
                actor if mode == "direct" else tiny_actor(),
                nets,
                mode=mode,
                critic_input="residual",
                **kwargs,
            )
