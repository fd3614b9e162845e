"""The critic algorithms' fixes against their references: FQL distils mu's unclipped output (a unit past
a bound still feels the distillation), QC clips its proposals before the critics pick, and DSRL's
discount applies per chunk decision (its TD target against a hand computation)."""

from __future__ import annotations

import pytest
import torch
from doubles.episodes import GAMMA, make_episodes
from omegaconf import OmegaConf
from tensordict import TensorDict

from l1flow_rl import BestOfNActor, FQLLoss, L1FlowActor, OneStepActor
from l1flow_rl.commands.cli import compose_config
from l1flow_rl.finetune.buffers import RLBuffers
from l1flow_rl.finetune.registry import get_algorithm
from l1flow_rl.networks.critic import ChunkCritic


def summing_critic(flow, input_shape) -> ChunkCritic:
    """One critic with a linear head: Q = sum of its (action) input, the observation ignored."""
    critic = ChunkCritic.from_policy(flow, input_shape=input_shape, num_critics=1, hidden_dims=())
    layer = critic.heads.layers[0]
    with torch.no_grad():
        layer.weight.zero_()
        layer.weight[:, layer.weight.shape[1] - torch.Size(input_shape).numel() :] = 1.0
        layer.bias.zero_()
    return critic


# -- FQL ---------------------------------------------------------------------------------------------


def test_fql_a_saturated_unit_still_receives_the_distillation_gradient():
    """mu's output for one executed unit sits at 5 (past the bound 1): the critics value it clipped (no
    Q gradient there), and the distillation pulls the raw 5 toward the teacher's chunk (here 0)."""
    flow = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
    mu = OneStepActor.from_flow(flow, hidden_dims=(16,))
    h, a = 8, 2  # 16 x 2 chunk; the executed steps are [1, 9)
    last = mu.policy.net[-1]
    unit = 1 * a + 0  # step 1 (the first executed), action 0
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()
        last.bias[unit] = 5.0  # every chunk: 5 at that unit, 0 elsewhere
    alpha = 3.0
    loss = FQLLoss(mu, flow, summing_critic(flow, (h, a)), alpha=alpha)
    loss.teacher_chunk = lambda obs, z: torch.zeros_like(z)
    td = TensorDict({"observation": torch.randn(4, 2, 5)}, [4])
    actor_loss, _ = loss.actor_loss(td)
    actor_loss.backward()
    # d/db alpha * mean((x - 0)^2) over 4 x 16 x 2 entries, 4 of them at 5: alpha * 2 * 5 * 4 / 128;
    # the Q term adds nothing (the critics read the clipped 1)
    assert last.bias.grad[unit].item() == pytest.approx(alpha * 2 * 5.0 * 4 / (4 * 16 * 2), rel=1e-5)
    # a unit inside the bounds gets the Q gradient (lambda = 1 / mean|Q| = 1 / 1 here, minus sign)
    inside = 2 * a + 0
    assert last.bias.grad[inside].item() == pytest.approx(-1.0 / 4 * 4, rel=1e-5)
    # what mu executes is clipped: the unit acts at the bound
    acted = mu(td)["action_chunk"]
    assert acted[:, 0, 0].eq(1.0).all() and acted.abs().max() <= 1.0


# -- QC ----------------------------------------------------------------------------------------------


def test_qc_clips_its_proposals_before_the_critics_pick():
    """Two proposals under Q = sum of the executed chunk: one inside the bounds (every action 0.9), one
    with a single entry far past them (100, the rest -0.5). Unclipped the critics would rank the second
    first (its raw sum 92.5 against 14.4); clipped it sums to -6.5 and the first is picked."""
    flow = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
    flow.policy.sampler.__class__ = type(
        "Identity", (type(flow.policy.sampler),), {"__call__": lambda self, denoise, x, **kw: x}
    )  # the proposal is its noise
    critic = summing_critic(flow, (8, 2))
    seen = []
    critic.register_forward_hook(lambda module, args, out: seen.append(args[1].detach().clone()))
    best = BestOfNActor(flow, critic, num_samples=2, rl_horizon=8)
    inside = torch.full((16, 2), 0.9)
    wild = torch.full((16, 2), -0.5)
    wild[1, 0] = 100.0
    noise = torch.stack([inside, wild]).expand(3, 2, 16, 2).clone()
    obs = flow.policy.as_obs_dict(torch.randn(3, 2, 5))
    chunks = best.propose(obs, noise=noise)
    assert chunks.abs().max() <= 1.0 and torch.equal(chunks[:, 0], inside.expand(3, 16, 2))
    assert best.pick(obs, chunks).tolist() == [0, 0, 0]
    assert seen and all(x.abs().max() <= 1.0 for x in seen)  # the critics never saw a value past a bound


@pytest.mark.parametrize("num_samples", [8, 32])
def test_qc_keeps_its_number_of_proposals_configurable(num_samples):
    cfg = compose_config(
        ["finetune=qc", "checkpoint=bc.pt", f"finetune.qc.num_samples={num_samples}"], command="finetune"
    )
    flow = L1FlowActor.for_state(obs_dim=3, action_dim=2, down_dims=(8, 16))
    small = OmegaConf.merge(cfg.finetune, {"critic_hidden_dims": [16]})
    assert get_algorithm("qc").build(flow, small).actor.num_samples == num_samples


# -- DSRL --------------------------------------------------------------------------------------------

H = 4
LENGTHS, TERMINATED = (6, 9), (True, False)  # make_episodes' defaults


def dsrl_target_by_hand(e: int, t: int, q_next: float, per_chunk: bool) -> float:
    """DSRL's chunk MDP: the chunk's rewards (1 + t + 10 e) summed, gamma once per chunk; per env step:
    each reward discounted, gamma^h on the bootstrap."""
    length, terminated = LENGTHS[e], TERMINATED[e]
    steps = range(min(H, length - t))
    if per_chunk:
        ret, discount = sum(1 + (t + i) + 10 * e for i in steps), GAMMA
    else:
        ret, discount = sum(GAMMA**i * (1 + (t + i) + 10 * e) for i in steps), GAMMA**H
    reaches_terminal_end = terminated and t + H >= length
    return ret + (0.0 if reaches_terminal_end else discount * q_next)


@pytest.mark.parametrize("per_chunk", [True, False])
def test_dsrl_discounts_per_chunk_decision_by_default(per_chunk):
    overrides = [
        "finetune=dsrl",
        "checkpoint=bc.pt",
        "finetune.reward=recorded",
        f"finetune.gamma={GAMMA}",
        f"finetune.rl_horizon={H}",
        "finetune.batch_size=500",
        "finetune.critic_hidden_dims=[16]",
        "finetune.dsrl.actor_hidden_dims=[16]",
    ]
    if not per_chunk:
        overrides.append("finetune.dsrl.discount_per_chunk=false")
    cfg = compose_config(overrides, command="finetune")
    assert cfg.finetune.dsrl.discount_per_chunk is per_chunk  # the preset says it
    algorithm = get_algorithm("dsrl")
    options = algorithm.buffer_options(cfg.finetune)
    batch = RLBuffers(cfg, make_episodes(LENGTHS, TERMINATED), H, seed=0, **options).sample_offline()
    flow = L1FlowActor.for_state(obs_dim=2, action_dim=3, down_dims=(8, 16))
    loss = algorithm.build(flow, cfg.finetune)
    q_next = 2.0
    loss.next_value = lambda td, next_obs: torch.full((next_obs.shape[0],), q_next)
    target = loss.td_target(batch)
    seen = set()
    for i in range(batch.shape[0]):
        e, t = int(batch["episode"][i]), int(batch["step"][i])
        assert target[i].item() == pytest.approx(dsrl_target_by_hand(e, t, q_next, per_chunk), rel=1e-5), (
            e,
            t,
        )
        seen.add((e, t))
    assert {(0, 2), (0, 4), (1, 5)} <= seen  # the terminal end reached exactly and crossed; a bootstrap
