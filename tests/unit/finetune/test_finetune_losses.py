"""The fine-tuning losses: TD targets against hand computations at terminated and truncated ends, QC's
pick-online / value-target backup, the steering actor's bounds with the flow left untouched, FQL's
gradient routing."""

from __future__ import annotations

import pytest
import torch
from doubles.episodes import GAMMA, make_episodes
from tensordict import TensorDict

from l1flow_rl import (
    ChunkCriticLoss,
    DSRLLoss,
    DSRLNALoss,
    FQLLoss,
    L1FlowActor,
    NoiseActor,
    OneStepActor,
    QCLoss,
)
from l1flow_rl.data import make_chunk_buffer
from l1flow_rl.finetune.proposal_cache import ProposalCache
from l1flow_rl.networks.critic import ChunkCritic

H_EXEC = 4


def linear_critic(flow, input_shape, biases, action_weight=0.0, normalize_input=True):
    """A critic with linear heads (no hidden layer): Q_e = action_weight * sum(input) + biases[e]."""
    critic = ChunkCritic.from_policy(
        flow,
        input_shape=input_shape,
        num_critics=len(biases),
        hidden_dims=(),
        normalize_input=normalize_input,
    )
    layer = critic.heads.layers[0]
    with torch.no_grad():
        layer.weight.zero_()
        obs_part = layer.weight.shape[1] - torch.Size(input_shape).numel()
        layer.weight[:, obs_part:] = action_weight
        layer.bias.copy_(torch.tensor(biases, dtype=torch.float32).reshape(-1, 1, 1))
    return critic


def train(loss, optim, batch, steps: int) -> None:
    """``steps`` updates of every ``loss_*`` term of ``loss`` on one batch."""
    for _ in range(steps):
        out = loss(batch)
        optim.zero_grad()
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        optim.step()


def window_batch(h=H_EXEC):
    """Windows of two hand-made episodes (make_episodes: L = 6 terminated, L = 9 truncated)."""
    rb = make_chunk_buffer(
        make_episodes(), obs_horizon=2, pred_horizon=8, batch_size=2000, seed=0, rl_horizon=h, gamma=GAMMA
    )
    return rb.sample()


def hand_target(e: int, t: int, q_next: float, h: int = H_EXEC) -> float:
    """R_h summed inside the episode, plus gamma^h Q unless the chunk reaches episode 0's terminal end."""
    length, terminated = {0: (6, True), 1: (9, False)}[e]
    ret = sum(GAMMA**i * (1 + (t + i) + 10 * e) for i in range(min(h, length - t)))
    reaches_end = t + h >= length
    return ret + (0.0 if (terminated and reaches_end) else GAMMA**h * q_next)


@pytest.mark.parametrize("q_agg,q_next", [("mean", 2.0), ("min", 1.0)])
def test_td_target_by_hand_at_terminated_and_truncated_ends(q_agg, q_next):
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    critic = linear_critic(flow, (H_EXEC, 3), biases=[1.0, 3.0])  # target values 1 and 3 everywhere
    loss = ChunkCriticLoss(
        critic, flow, next_actor=lambda obs: torch.zeros(obs.shape[0], H_EXEC, 3), gamma=GAMMA, q_agg=q_agg
    )
    batch = window_batch()
    target = loss.td_target(batch)
    valid = batch["chunk_valid"].reshape(-1)
    seen = set()
    for i in range(batch.shape[0]):
        e, t = int(batch["episode"][i]), int(batch["step"][i])
        assert target[i].item() == pytest.approx(hand_target(e, t, q_next), rel=1e-5), (e, t)
        seen.add((e, t, bool(valid[i])))
    # the cases that decide: the terminated end reached exactly and crossed (valid, no bootstrap),
    # the truncated end reached exactly (valid, bootstrapped) and crossed (left out)
    assert {(0, 2, True), (0, 4, True), (1, 5, True), (1, 7, False)} <= seen
    out = loss(batch)
    assert out["valid_fraction"].item() == pytest.approx(valid.float().mean().item())


def test_target_critics_draw_a_random_subset_of_the_ensemble_for_each_bootstrap():
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    biases = [float(b) for b in range(10)]  # member e values everything at e
    critic = linear_critic(flow, (H_EXEC, 3), biases=biases)
    zeros = lambda obs: torch.zeros(obs.shape[0], H_EXEC, 3)  # noqa: E731
    loss = ChunkCriticLoss(critic, flow, next_actor=zeros, gamma=GAMMA, q_agg="min", target_critics=2)
    obs = flow.policy.as_obs_dict(torch.randn(4, 2, 2))
    torch.manual_seed(0)
    drawn = {loss.next_value(None, obs)[0].item() for _ in range(200)}
    # min over 2 of 10 members: never the largest member alone, every smaller one at times
    assert drawn == set(biases[:9])
    everyone = ChunkCriticLoss(critic, flow, next_actor=zeros, q_agg="min")
    assert everyone.next_value(None, obs).tolist() == [0.0] * 4
    with pytest.raises(ValueError, match=r"target_critics=11 must lie in \[1, num_critics=10\]"):
        ChunkCriticLoss(critic, flow, next_actor=zeros, target_critics=11)


def test_critic_loss_ignores_invalid_windows():
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    loss = ChunkCriticLoss(
        ChunkCritic.from_policy(flow, input_shape=(H_EXEC, 3), hidden_dims=(16,)),
        flow,
        next_actor=lambda obs: torch.zeros(obs.shape[0], H_EXEC, 3),
    )
    batch = window_batch()[:64]
    base = loss(batch)["loss_qvalue"]
    poisoned = batch.clone()
    invalid = ~poisoned["chunk_valid"].reshape(-1)
    assert invalid.any()
    poisoned["next", "reward"][invalid] = 1e6  # rewards of left-out windows change nothing
    assert loss(poisoned)["loss_qvalue"].item() == pytest.approx(base.item(), rel=1e-6)


def test_qc_picks_with_the_online_critics_and_values_with_the_target_critics():
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    # online critics: Q = +sum(chunk); target critics: Q = -sum(chunk) - disagreeing on purpose
    loss = QCLoss(flow, linear_critic(flow, (H_EXEC, 3), [0.0, 0.0], action_weight=1.0), num_samples=2)
    with torch.no_grad():
        loss.target_qvalue_network_params["module", "heads", "layers", "0", "weight"][:, -H_EXEC * 3 :] = -1.0

    def propose(obs, num_samples=None):  # two proposals: every action -0.5, or every action +0.5
        low, high = torch.full((8, 3), -0.5), torch.full((8, 3), 0.5)
        return torch.stack([low, high]).expand(obs.shape[0], 2, 8, 3)

    loss.actor.propose = propose
    obs = flow.policy.as_obs_dict(torch.randn(5, 2, 2))
    value = loss.next_value(None, obs)
    # the online critics pick the +0.5 chunk; the target critics value it at -0.5 * h * A
    assert torch.allclose(value, torch.full((5,), -0.5 * H_EXEC * 3))
    # picking with the target critics would have chosen -0.5 and valued it at +6
    acted = loss.actor(TensorDict({"observation": torch.randn(5, 2, 2)}, [5]))["action_chunk"]
    assert torch.all(acted == 0.5)


def test_qc_trains_the_flow_unless_frozen():
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    critic = ChunkCritic.from_policy(flow, input_shape=(H_EXEC, 3), hidden_dims=(16,))
    batch = window_batch()[:32]
    trained = QCLoss(flow, critic, num_samples=4)
    flow_params = {id(p) for p in flow.parameters()}
    assert flow_params <= {id(p) for p in trained.parameters()}
    assert "loss_bc" in trained(batch)
    frozen_flow = L1FlowActor.for_state(
        obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16)
    )
    frozen = QCLoss(frozen_flow, critic, num_samples=4, freeze_flow=True)
    assert not {id(p) for p in frozen_flow.parameters()} & {id(p) for p in frozen.parameters()}
    assert "loss_bc" not in frozen(batch)


def test_fql_distillation_sends_no_gradient_to_the_teacher():
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    mu = OneStepActor.from_flow(flow, hidden_dims=(32,))
    loss = FQLLoss(mu, flow, ChunkCritic.from_policy(flow, input_shape=(H_EXEC, 3), hidden_dims=(16,)))
    batch = window_batch()[:32]
    loss_actor, meta = loss.actor_loss(batch)
    loss_actor.backward()
    assert all(p.grad is None for p in flow.parameters())  # teacher: no gradient from distillation
    assert all(p.grad is None for p in loss.qvalue_network_params.values(True, True))  # nor the critics
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in mu.parameters())
    assert meta["lambda"].item() > 0 and meta["distill_loss"].item() > 0
    loss.bc_loss(batch)["loss_l1flow"].backward()  # the BC flow trains by its own loss
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in flow.parameters())


def test_steering_noise_stays_in_bounds_and_the_flow_stays_unchanged():
    torch.manual_seed(0)
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    before = {k: v.clone() for k, v in flow.state_dict().items()}
    steer = NoiseActor.from_flow(flow, bound=1.5, hidden_dims=(32,))
    critic = ChunkCritic.from_policy(flow, input_shape=(8, 3), hidden_dims=(32,), normalize_input=False)
    loss = DSRLLoss(steer, critic, gamma=GAMMA, init_alpha=1e-3)
    assert not {id(p) for p in flow.parameters()} & {id(p) for p in loss.parameters()}
    optim = torch.optim.Adam(loss.parameters(), lr=1e-2)
    batch = window_batch()[:64]
    # noise the collector would have stored, and rewards that pay for large noise: the actor is pushed
    # towards the bound
    batch["noise"] = torch.rand(64, 8, 3) * 3 - 1.5
    batch["next", "reward"] = batch["noise"].sum((1, 2)).unsqueeze(-1)
    train(loss, optim, batch, 60)
    for k, v in flow.state_dict().items():
        assert torch.equal(v, before[k]), k
    acted = steer(TensorDict({"observation": torch.randn(256, 2, 2)}, [256]))
    noise = acted["noise_chunk"][:, 0]
    assert torch.equal(acted["noise_chunk"], noise.unsqueeze(1).expand(-1, 4, 8, 3))  # one w per chunk
    assert noise.abs().max() <= 1.5
    assert noise.mean() > 0.3  # the actor did move (towards the rewarded +bound)
    # the executed chunk is the flow's decoding of the chosen noise
    obs = flow.policy.as_obs_dict(acted["observation"])
    assert torch.allclose(acted["action_chunk"], flow.policy.executable(steer.decode(obs, noise)))


def test_the_steering_actor_and_its_critic_must_take_the_flows_noise_shape():
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    steer = NoiseActor.from_flow(flow, bound=1.5, hidden_dims=(16,))
    assert steer.noise_policy.noise_shape == (8, 3)  # the flow's whole input noise H x A
    critic = ChunkCritic.from_policy(flow, input_shape=(8, 3), hidden_dims=(8,), normalize_input=False)
    DSRLLoss(steer, critic)
    window_critic = ChunkCritic.from_policy(flow, input_shape=(4, 3), hidden_dims=(8,), normalize_input=False)
    with pytest.raises(ValueError, match=r"input_shape=\[8, 3\]"):
        DSRLLoss(steer, window_critic)
    with pytest.raises(ValueError, match=r"must be the flow's noise \[H, A\] = \[8, 3\]"):
        NoiseActor(flow, steer.prior().noise_policy.__class__((4, 3), 1.5))


def test_steering_under_the_multi_step_wrapper_gives_each_step_its_chunk_noise_and_counter():
    from torchrl.modules import MultiStepActorWrapper

    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    steer = NoiseActor.from_flow(flow, hidden_dims=(16,))
    acting = MultiStepActorWrapper(steer, n_steps=4)
    td = TensorDict({"observation": torch.randn(2, 2, 2), "is_init": torch.ones(2, 1, dtype=torch.bool)}, [2])
    seen = []
    for _ in range(5):
        td = acting(td)
        seen.append((int(td["counter"][0]), td["noise"].clone(), td["action"].clone()))
        td["is_init"] = torch.zeros(2, 1, dtype=torch.bool)
    assert [c for c, _, _ in seen] == [1, 2, 3, 4, 1]  # a new chunk every 4 steps
    assert all(torch.equal(seen[0][1], n) for _, n, _ in seen[1:4]) and not torch.equal(
        seen[0][1], seen[4][1]
    )
    # DSRL values only windows that start a chunk
    loss = DSRLLoss(
        steer, ChunkCritic.from_policy(flow, input_shape=(8, 3), hidden_dims=(8,), normalize_input=False)
    )
    batch = TensorDict(
        {"counter": torch.tensor([[1], [2], [1]]), "chunk_valid": torch.tensor([[True], [True], [False]])},
        [3],
    )
    assert loss.valid(batch, 3).tolist() == [True, False, False]


def test_frozen_qc_draws_each_observations_proposals_once_and_reproducibly():
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    critic = linear_critic(flow, (H_EXEC, 3), [0.0, 0.0], action_weight=1.0)
    loss = QCLoss(flow, critic, num_samples=5, freeze_flow=True, cache_seed=3)
    calls = []
    real_propose = loss.actor.propose

    def counting_propose(obs, num_samples=None, noise=None):
        calls.append(obs.shape[0])
        return real_propose(obs, num_samples, noise=noise)

    loss.actor.propose = counting_propose
    obs = flow.policy.as_obs_dict(torch.randn(6, 2, 2))
    repeated = obs[[0, 1, 2, 3, 4, 5, 0, 0]]  # a batch may hold one observation twice
    first = loss.next_value(None, repeated)
    assert calls == [16] and len(loss.proposal_cache) == 6  # one block of 16 (6 observations, padded)
    assert loss.next_value(None, obs[[5, 0]]).tolist() == first[[5, 0]].tolist()
    assert calls == [16]  # served from the cache: no flow call
    cache = loss.proposal_cache
    assert (cache.hits, cache.misses) == (4, 6)
    out = loss(window_batch()[:16])
    assert 0.0 < out["proposal_cache_hit_rate"].item() < 1.0 and "loss_bc" not in out
    # the backup is the best cached proposal under the online critics (Q = sum of the chunk)
    executed = cache(obs)
    best = executed.sum((-1, -2)).max(1).values
    assert torch.allclose(loss.next_value(None, obs), best)
    # a fresh cache (a resumed run) draws the same proposals; another seed draws others
    again = QCLoss(flow, critic, num_samples=5, freeze_flow=True, cache_seed=3).proposal_cache
    assert torch.equal(again(obs), executed)
    other = QCLoss(flow, critic, num_samples=5, freeze_flow=True, cache_seed=4).proposal_cache
    assert not torch.equal(other(obs), executed)
    with pytest.raises(ValueError, match=r"noise must have shape \[6, 5, 8, 3\]"):
        real_propose(obs, noise=torch.zeros(6, 4, 8, 3))


def test_cached_proposals_do_not_depend_on_the_batch_they_were_drawn_in():
    """An observation met alone, or among 40 others, gets the same proposals bit for bit (the UNet's
    batched kernels round differently at other batch sizes): what makes a resumed run exact."""
    torch.manual_seed(0)
    flow = L1FlowActor.for_state(
        obs_dim=5, action_dim=4, action_steps=H_EXEC, down_dims=(16, 32), timestep_embed_dim=16
    )
    critic = ChunkCritic.from_policy(flow, input_shape=(H_EXEC, 4), hidden_dims=(8,))
    obs = flow.policy.as_obs_dict(torch.randn(40, 2, 5))
    together = QCLoss(flow, critic, num_samples=3, freeze_flow=True).proposal_cache(obs)
    for rows in ([7], [3, 30, 12], list(range(20, 37))):
        alone = QCLoss(flow, critic, num_samples=3, freeze_flow=True).proposal_cache(obs[rows])
        assert torch.equal(alone, together[rows]), rows
    with pytest.raises(ValueError, match="block must be >= 1"):
        ProposalCache(lambda obs, noise: noise, noise_shape=(3, 16, 4), block=0)


def test_unfrozen_qc_keeps_no_cache():
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    critic = ChunkCritic.from_policy(flow, input_shape=(H_EXEC, 3), hidden_dims=(16,))
    loss = QCLoss(flow, critic, num_samples=4)
    assert loss.proposal_cache is None and "proposal_cache_hit_rate" not in loss(window_batch()[:8])


def _dsrl_na(flow, critic, noise_critic=None, **kwargs):
    steer = NoiseActor.from_flow(flow, bound=1.5, hidden_dims=(16,))
    noise_critic = noise_critic or ChunkCritic.from_policy(
        flow, input_shape=(8, 3), hidden_dims=(16,), normalize_input=False
    )
    return DSRLNALoss(steer, critic, noise_critic, **kwargs)


def test_dsrl_na_bootstraps_the_action_critic_on_the_decoded_steering_noise():
    """y = R_h + gamma^h (1 - terminated) (min Qbar^A(s', decode(s', w')) - alpha log pi(w' | s')), at
    both episode ends; the chunk valued is the flow's decoding of the actor's w', clipped to the bound."""
    torch.manual_seed(0)
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    loss = _dsrl_na(flow, linear_critic(flow, (H_EXEC, 3), biases=[1.0, 3.0]), gamma=GAMMA, init_alpha=0.5)
    log_prob = -2.0
    loss._sample = lambda obs: (torch.full((obs.shape[0], 8, 3), 9.0), torch.full((obs.shape[0],), log_prob))
    batch = window_batch()
    target = loss.td_target(batch)
    q_next = 1.0 - 0.5 * log_prob  # min over the constant members, minus alpha log pi
    for i in range(batch.shape[0]):
        e, t = int(batch["episode"][i]), int(batch["step"][i])
        assert target[i].item() == pytest.approx(hand_target(e, t, q_next), rel=1e-5), (e, t)
    # with an action-weighted target critic, the value is that of the chunk decoded from the clipped w'
    with torch.no_grad():
        loss.target_qvalue_network_params["module", "heads", "layers", "0", "weight"][:, -H_EXEC * 3 :] = 1.0
    obs = flow.policy.as_obs_dict(torch.randn(5, 2, 2))
    chunk = loss.executed(loss.actor.decode(obs, torch.full((5, 8, 3), 1.5)))
    expected = torch.minimum(chunk.sum((1, 2)) + 1.0, chunk.sum((1, 2)) + 3.0) - 0.5 * log_prob
    assert torch.allclose(loss.next_value(None, obs), expected, atol=1e-5)


def test_dsrl_na_distils_the_action_critic_of_each_cached_noises_chunk():
    """Q^W is fitted on each observation's cached noises, and on the actor's, against min Q^A of their
    decoded chunks; the cached noises are drawn and decoded once per observation, and a fresh cache
    draws the same ones."""
    torch.manual_seed(0)
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    critic = linear_critic(flow, (H_EXEC, 3), biases=[0.0, 2.0], action_weight=1.0)
    loss = _dsrl_na(flow, critic, distill_samples=3, cache_seed=5)
    batch = window_batch()[:16]
    obs = loss.read_observation(batch, "observation")
    keys = loss.proposal_cache.keys(obs)
    noise = torch.stack([loss.proposal_cache.noise(k) for k in keys]).clamp(-1.5, 1.5)  # [16, 3, 8, 3]
    flat = obs.unsqueeze(1).expand(16, 3, *obs.shape[1:]).reshape(48, *obs.shape[1:])
    chunks = loss.executed(loss.actor.decode(flat, noise.flatten(0, 1)))
    expected = chunks.sum((1, 2)).mean()  # min over the members: the bias-0 one
    out = loss(batch)
    assert out["distill_target_mean"].item() == pytest.approx(expected.item(), rel=1e-5)
    # the other half of the fit: Q^A of the chunk decoded from the actor's own (clipped) noise
    real_sample = loss._sample
    loss._sample = lambda obs: (torch.full((obs.shape[0], 8, 3), 0.7), torch.zeros(obs.shape[0]))
    on_actor = loss.executed(loss.actor.decode(obs, torch.full((16, 8, 3), 0.7))).sum((1, 2)).mean()
    assert loss(batch)["distill_target_actor_mean"].item() == pytest.approx(on_actor.item(), rel=1e-5)
    loss._sample = real_sample
    distinct = len(set(keys))
    assert len(loss.proposal_cache) == distinct and loss.proposal_cache.misses == distinct
    loss(batch)
    assert loss.proposal_cache.misses == distinct  # served from the cache: no new decoding
    # the distillation's gradient reaches the noise critic only, the actor's the noise policy only
    loss.zero_grad()
    out = loss(batch)
    out["loss_noise_qvalue"].backward()
    grads = lambda params: [p.grad for p in params.values(True, True)]  # noqa: E731
    assert all(g is None or g.abs().sum() == 0 for g in grads(loss.qvalue_network_params))
    assert any(g is not None and g.abs().sum() > 0 for g in grads(loss.noise_qvalue_network_params))
    assert all(g is None for g in grads(loss.actor_network_params))
    again = _dsrl_na(flow, critic, distill_samples=3, cache_seed=5)
    assert torch.equal(again.proposal_cache(obs), loss.proposal_cache(obs))


def test_dsrl_na_steers_within_the_bound_and_leaves_the_flow_as_it_was():
    torch.manual_seed(0)
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    before = {k: v.clone() for k, v in flow.state_dict().items()}
    critic = ChunkCritic.from_policy(flow, input_shape=(H_EXEC, 3), hidden_dims=(32,))
    loss = _dsrl_na(flow, critic, gamma=GAMMA)
    assert not {id(p) for p in flow.parameters()} & {id(p) for p in loss.parameters()}
    steer_before = {k: v.clone() for k, v in loss.actor.noise_policy.state_dict().items()}
    optim = torch.optim.Adam(loss.parameters(), lr=1e-2)
    batch = window_batch()[:32]
    batch["next", "reward"] = batch["action_chunk"][:, 1:5].sum((1, 2)).unsqueeze(-1)  # pays for actions
    train(loss, optim, batch, 10)
    for k, v in flow.state_dict().items():
        assert torch.equal(v, before[k]), k
    assert any(not torch.equal(v, steer_before[k]) for k, v in loss.actor.noise_policy.state_dict().items())
    acted = loss.actor(TensorDict({"observation": torch.randn(64, 2, 2)}, [64]))
    assert acted["noise_chunk"].abs().max() <= 1.5


def test_dsrl_na_checks_its_critics_shapes():
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    action_critic = ChunkCritic.from_policy(flow, input_shape=(H_EXEC, 3), hidden_dims=(8,))
    window_noise = ChunkCritic.from_policy(flow, input_shape=(4, 3), hidden_dims=(8,), normalize_input=False)
    with pytest.raises(ValueError, match=r"noise critic .* input_shape=\[8, 3\] and normalize_input=False"):
        _dsrl_na(flow, action_critic, window_noise)
    raw = ChunkCritic.from_policy(flow, input_shape=(H_EXEC, 3), hidden_dims=(8,), normalize_input=False)
    with pytest.raises(ValueError, match="action critic values executed chunks"):
        _dsrl_na(flow, raw)
    with pytest.raises(ValueError, match="distill_samples must be >= 1"):
        _dsrl_na(flow, action_critic, distill_samples=0)
