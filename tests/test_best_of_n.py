"""BestOfNActor (Q-chunking's best-of-N selection) and the flow-Q trainer's best_of_n mode, without a
simulator: the choice is the argmax of the critics' mean over the policy's own draws, the actor
follows the critics as they train, and a saved run reloads as the same selecting actor."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from l1flow_rl import L1FlowActor
from l1flow_rl.config import AppConfig
from l1flow_rl.networks.best_of_n import BestOfNActor
from l1flow_rl.networks.critic import build_critics, stack_critics
from l1flow_rl.workspace.flowq_trainer import FlowQTrainer, finetuned_policy_config

TO, H, K, D, A = 2, 8, 4, 3, 2


def tiny_actor() -> L1FlowActor:
    return L1FlowActor.for_state(
        obs_dim=D, action_dim=A, obs_horizon=TO, pred_horizon=H, action_steps=K, down_dims=(8, 16)
    )


def test_the_chosen_chunk_is_the_draw_the_ensemble_values_most():
    torch.manual_seed(0)
    actor = tiny_actor()
    critics = build_critics(actor, num=2, action_horizon=3, hidden_dims=(16,))
    best = BestOfNActor(actor, critics[0], stack_critics(critics), num_samples=6, rl_horizon=3)
    obs = torch.randn(5, TO, D)
    chosen, draws, scores = best.select(obs)
    assert chosen.shape == (5, K, A) and draws.shape == (5, 6, K, A) and scores.shape == (5, 6)
    # the scores by hand: each critic on (observation, first h executed steps), averaged
    with torch.no_grad():
        rep = obs.repeat_interleave(6, 0)
        hand = sum(c.module(rep, draws.reshape(30, K, A)[:, :3]) for c in critics).reshape(5, 6) / 2
    torch.testing.assert_close(scores, hand)
    torch.testing.assert_close(chosen, draws[torch.arange(5), hand.argmax(1)])
    assert len({tuple(d.flatten().tolist()) for d in draws[0]}) == 6  # 6 distinct draws
    # forward writes the choice under the actor's key, for any batch shape
    torch.manual_seed(1)
    out = best(TensorDict({"observation": obs.reshape(5, 1, TO, D)}, [5, 1]))["action_chunk"]
    torch.manual_seed(1)
    torch.testing.assert_close(out.reshape(5, K, A), best.select(obs)[0])
    # one draw is the policy itself
    one = BestOfNActor(actor, critics[0], stack_critics(critics), num_samples=1, rl_horizon=3)
    torch.manual_seed(2)
    a = one(TensorDict({"observation": obs}, [5]))["action_chunk"]
    torch.manual_seed(2)
    torch.testing.assert_close(a, actor(TensorDict({"observation": obs}, [5]))["action_chunk"])


def test_bad_settings_are_named():
    actor = tiny_actor()
    critics = build_critics(actor, num=2, action_horizon=K, hidden_dims=(16,))
    with pytest.raises(ValueError, match="num_samples must be >= 1"):
        BestOfNActor(actor, critics[0], stack_critics(critics), num_samples=0, rl_horizon=K)
    with pytest.raises(ValueError, match=r"rl_horizon=5 must lie in \[1, action_steps=4\]"):
        BestOfNActor(actor, critics[0], stack_critics(critics), num_samples=2, rl_horizon=5)
    with pytest.raises(ValueError, match="stacked along one leading ensemble dim"):
        BestOfNActor(actor, critics[0], stack_critics(critics)[0], num_samples=2, rl_horizon=K)


def test_trainer_best_of_n_selects_with_the_critics_it_trains(tmp_path):
    from l1flow_rl.workspace.build import build_actor

    cfg = OmegaConf.structured(AppConfig)
    cfg.policy.obs_horizon, cfg.policy.pred_horizon, cfg.policy.action_steps = TO, H, K
    cfg.policy.down_dims, cfg.policy.timestep_embed_dim = [8, 16], 8
    cfg.finetune.mode, cfg.finetune.num_samples, cfg.finetune.critic_hidden_dims = "best_of_n", 4, [16]
    bc = build_actor(cfg.policy, {"state": (D,)}, A)  # the network the saved config describes
    trainer = FlowQTrainer(bc, cfg.finetune)
    deployed = trainer.policy_actor
    assert isinstance(deployed, BestOfNActor) and deployed.actor is trainer.actor
    assert not any(p.requires_grad for p in trainer.actor.parameters())
    # the deployed actor reads the loss's critic parameters themselves: an update moves its scores
    obs = torch.randn(3, TO, D)
    chunks = torch.rand(3, K, A) * 2 - 1
    before = deployed.q_values(obs, chunks).clone()
    td = TensorDict(
        {
            "observation": torch.randn(8, TO, D),
            "action_chunk": torch.rand(8, H, A) * 2 - 1,
            "next": {
                "observation": torch.randn(8, TO, D),
                "reward": torch.rand(8, 1),
                "done": torch.zeros(8, 1, dtype=torch.bool),
                "terminated": torch.zeros(8, 1, dtype=torch.bool),
            },
        },
        [8],
    )
    actor0 = {k: v.clone() for k, v in trainer.actor.state_dict().items()}
    metrics = trainer.update(td)  # actor=True is ignored: nothing but the critics trains
    assert "loss_actor" not in metrics
    assert not torch.equal(before, deployed.q_values(obs, chunks))
    assert all(torch.equal(v, actor0[k]) for k, v in trainer.actor.state_dict().items())
    assert trainer.bc_distance(td, generator=torch.Generator().manual_seed(0)) >= 0
    # saved as a finetune run saves it, reloaded as the same selecting actor
    block = {"num_samples": 4, "rl_horizon": K, "num_qvalue_nets": 2, "critic_hidden_dims": [16]}
    policy_cfg = finetuned_policy_config(OmegaConf.to_container(cfg.policy), "best_of_n", block)
    assert policy_cfg["best_of_n"] == block and policy_cfg["name"].endswith("_qc")
    loaded = _saved_and_reloaded(tmp_path / "ft.pt", deployed, cfg, policy_cfg)
    assert isinstance(loaded, BestOfNActor) and loaded.num_samples == 4
    torch.testing.assert_close(loaded.q_values(obs, chunks), deployed.q_values(obs, chunks))
    torch.manual_seed(3)
    mine = deployed(TensorDict({"observation": obs}, [3]))["action_chunk"]
    torch.manual_seed(3)
    torch.testing.assert_close(loaded(TensorDict({"observation": obs}, [3]))["action_chunk"], mine)
    assert loaded.with_sampler("euler", steps=1).sampler.nfe == 1


def test_residual_critics_read_the_chunk_minus_the_policys_own_in_the_loss_and_the_actor(tmp_path):
    """critic_input="residual": the critics read chunk - (the frozen policy's zero-noise chunk), the
    same in the loss (data chunks and TD targets) and in the selecting actor, which reloads with it;
    the residual of the policy's own zero-noise chunk is 0."""
    from l1flow_rl.workspace.build import build_actor

    torch.manual_seed(0)
    cfg = OmegaConf.structured(AppConfig)
    cfg.policy.obs_horizon, cfg.policy.pred_horizon, cfg.policy.action_steps = TO, H, K
    cfg.policy.down_dims, cfg.policy.timestep_embed_dim = [8, 16], 8
    cfg.finetune.mode, cfg.finetune.num_samples, cfg.finetune.critic_hidden_dims = "best_of_n", 4, [16]
    cfg.finetune.critic_input = "residual"
    trainer = FlowQTrainer(build_actor(cfg.policy, {"state": (D,)}, A), cfg.finetune)
    loss, deployed = trainer.loss, trainer.policy_actor
    assert loss.critic_input == deployed.critic_input == "residual"
    obs = torch.randn(5, TO, D)
    chunks = torch.rand(5, K, A) * 2 - 1
    own = trainer.actor.policy(obs, deterministic=True)[:, :K]
    od = loss.policy.as_obs_dict(obs)
    torch.testing.assert_close(loss.reference_chunk(od), own)
    torch.testing.assert_close(deployed.reference_chunk(obs), own)
    with torch.no_grad():
        hand = sum(c.module(obs, chunks - own) for c in _members(loss)).reshape(5) / 2
        in_loss = loss._q(od, chunks, loss.qvalue_network_params).mean(0).reshape(5)
    torch.testing.assert_close(in_loss, hand)
    torch.testing.assert_close(deployed.q_values(obs, chunks), hand)
    with torch.no_grad():  # the policy's own chunk is a zero residual
        zero = sum(c.module(obs, torch.zeros_like(own)) for c in _members(loss)).reshape(5) / 2
    torch.testing.assert_close(deployed.q_values(obs, own), zero)
    # and it saves and reloads as a residual selector
    block = {
        "num_samples": 4,
        "rl_horizon": K,
        "num_qvalue_nets": 2,
        "critic_hidden_dims": [16],
        "critic_input": "residual",
    }
    policy_cfg = finetuned_policy_config(OmegaConf.to_container(cfg.policy), "best_of_n", block)
    loaded = _saved_and_reloaded(tmp_path / "ft.pt", deployed, cfg, policy_cfg)
    assert loaded.critic_input == "residual"
    torch.testing.assert_close(loaded.q_values(obs, chunks), hand)
    with pytest.raises(ValueError, match="critic_input must be 'action' or 'residual'"):
        BestOfNActor(
            trainer.actor,
            _members(loss)[0],
            loss.qvalue_network_params,
            num_samples=2,
            rl_horizon=K,
            critic_input="delta",
        )


def _members(loss):
    """The ensemble's critics as modules with their own parameters (for scores by hand)."""
    import copy

    out = []
    for i in range(loss.num_qvalue_nets):
        member = copy.deepcopy(loss.qvalue_network)
        loss.qvalue_network_params[i].detach().to_module(member)
        out.append(member)
    return out


def _saved_and_reloaded(path, deployed, cfg, policy_cfg):
    """Save the selecting actor as a finetune run saves it, and load it back with ``load_actor``."""
    from l1flow_rl.workspace.checkpoint import load_actor, save_checkpoint

    state = {
        "model": deployed.state_dict(),
        "ema": None,
        "config": {**OmegaConf.to_container(cfg), "policy": policy_cfg},
        "obs_shapes": {"state": [D]},
        "action_dim": A,
    }
    save_checkpoint(path, state)
    return load_actor(path)[0]
