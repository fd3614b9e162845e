"""Fine-tuning data and updates without a simulator: the chunked TD target computed from real chunk
buffers against a hand computation, offline/online mixing, and FlowQTrainer in both modes."""

from __future__ import annotations

import copy

import pytest
import torch
from omegaconf import OmegaConf

from l1flow_rl import L1FlowActor
from l1flow_rl.config import AppConfig
from l1flow_rl.data import attach_metadata
from l1flow_rl.data.episodes import assemble_episode
from l1flow_rl.workspace.flowq_trainer import FlowQTrainer, finetuned_policy_config
from l1flow_rl.workspace.rl_data import RLBuffers

TO, H, K, D, A = 2, 8, 4, 2, 3
GAMMA = 0.9


def episodes(lengths=(5, 12), terminated=(True, False), episode_offset=0):
    """Episode e, step t: reward 1 + t; observations tagged with the episode."""
    parts = []
    for e, (n, term) in enumerate(zip(lengths, terminated)):
        t = torch.arange(n + 1, dtype=torch.float32)
        obs = torch.stack([(e + episode_offset) * 100 + t, -t], -1)
        parts.append(
            assemble_episode(
                e + episode_offset,
                obs[:n],
                torch.rand(n, A) * 2 - 1,
                reward=1 + torch.arange(n, dtype=torch.float32),
                terminated=term,
                final_observation=obs[n],
            )
        )
    meta = {"source": "hand.h5", "has_rewards": True, "has_final_observation": True, "control": "absolute"}
    return attach_metadata(torch.cat(parts), meta)


def run_cfg(**overrides):
    cfg = OmegaConf.structured(AppConfig)
    cfg.policy.obs_horizon, cfg.policy.pred_horizon, cfg.policy.action_steps = TO, H, K
    cfg.task.control = "absolute"
    cfg.finetune.batch_size = 512
    cfg.finetune.gamma = GAMMA
    cfg.finetune.critic_hidden_dims = [16]
    for key, value in overrides.items():
        OmegaConf.update(cfg, key, value)
    return cfg


def bc_actor() -> L1FlowActor:
    return L1FlowActor.for_state(
        obs_dim=D,
        action_dim=A,
        obs_horizon=TO,
        pred_horizon=H,
        action_steps=K,
        down_dims=(8, 16),
        timestep_embed_dim=8,
    )


def test_chunk_td_target_from_the_real_buffer_by_hand():
    """Episode 0: 5 steps, rewards 1..5, terminated; h = 3, gamma = 0.9; both critics output the
    constant c = 2, so target = R_h + gamma^3 * c unless the chunk reaches a terminal end, and the
    chunks at t = 3, 4 (t + h > 5) drop out of the critic loss."""
    cfg = run_cfg(**{"finetune.rl_horizon": 3, "finetune.num_qvalue_nets": 2})
    trainer = FlowQTrainer(bc_actor(), cfg.finetune)
    for p in trainer.loss.qvalue_network_params.values(True, True):
        p.data.zero_()
    last = ("module", "mlp", str(len(trainer.loss.qvalue_network.module.mlp) - 1), "bias")
    trainer.loss.qvalue_network_params.get(last).data.fill_(2.0)
    for key, value in trainer.loss.qvalue_network_params.items(True, True):  # targets = the critics
        trainer.loss.target_qvalue_network_params.get(key).data.copy_(value.data)
    buffers = RLBuffers(cfg, episodes(), rl_horizon=3, seed=0)
    batch = buffers.sample_offline()
    loss = trainer.loss
    loss.reduction = "none"
    per_sample, _ = loss.qvalue_loss(batch)
    for t, expected_target, valid in (
        (0, 1 + 0.9 * 2 + 0.81 * 3 + 0.729 * 2, True),  # inside the episode: bootstraps
        (2, 3 + 0.9 * 4 + 0.81 * 5, True),  # ends exactly at the terminal step: no bootstrap
        (3, None, False),  # runs past the end: masked
        (4, None, False),
    ):
        rows = ((batch["episode"] == 0) & (batch["step"] == t)).nonzero().squeeze(1)
        assert rows.numel(), f"window at t={t} not drawn"
        assert bool(batch["chunk_valid"][rows].all()) == valid
        if valid:
            torch.testing.assert_close(
                per_sample[rows], torch.full_like(per_sample[rows], 2 * (2 - expected_target) ** 2)
            )
        else:
            assert (per_sample[rows] == 0).all()
    # the 12-step episode is truncated, not terminated: its last full chunk (t = 9) bootstraps
    rows = ((batch["episode"] == 1) & (batch["step"] == 9)).nonzero().squeeze(1)
    target = 10 + 0.9 * 11 + 0.81 * 12 + 0.729 * 2
    torch.testing.assert_close(per_sample[rows], torch.full_like(per_sample[rows], 2 * (2 - target) ** 2))


def test_reward_shaping_maps_every_step_of_a_chunk():
    """reward_scale 0.5, reward_offset -1 per step on h = 3: the chunk return 1 + 0.9*2 + 0.81*3 of the
    window at t = 0 becomes sum_i 0.9^i (0.5 r_i - 1); the defaults ((r - 1) / 100) map, 0/1 do not."""
    cfg = run_cfg(**{"finetune.rl_horizon": 3, "finetune.reward_scale": 0.5, "finetune.reward_offset": -1.0})
    trainer = FlowQTrainer(bc_actor(), cfg.finetune)
    batch = RLBuffers(cfg, episodes(), rl_horizon=3, seed=0).sample_offline()
    rows = ((batch["episode"] == 0) & (batch["step"] == 0)).nonzero().squeeze(1)
    raw = batch["next", "reward"][rows].clone()
    torch.testing.assert_close(raw, torch.full_like(raw, 1 + 0.9 * 2 + 0.81 * 3))
    shaped = trainer.shape_rewards(batch)["next", "reward"][rows]
    expected = (0.5 * 1 - 1) + 0.9 * (0.5 * 2 - 1) + 0.81 * (0.5 * 3 - 1)
    torch.testing.assert_close(shaped, torch.full_like(shaped, expected))
    defaults = OmegaConf.structured(AppConfig).finetune
    assert (defaults.reward_scale, defaults.reward_offset) == (0.01, -0.01)
    plain = FlowQTrainer(
        bc_actor(), run_cfg(**{"finetune.reward_scale": 1.0, "finetune.reward_offset": 0.0}).finetune
    )
    again = RLBuffers(cfg, episodes(), rl_horizon=3, seed=0).sample_offline()
    before = again["next", "reward"].clone()
    assert torch.equal(plain.shape_rewards(again)["next", "reward"], before)


def test_sparse_reward_is_one_at_the_terminal_step_only():
    """finetune.reward=sparse, h = 3, gamma 0.9: episode 0 (5 steps, terminated) pays 1 at its last
    step only, so the window at t = 2 returns 0.81 and t = 0 returns 0; under the default map
    (r - 1) / 100 per step the t = 2 chunk is worth -0.01 - 0.009 + 0. The Monte-Carlo return of
    t = 0 is 0.9^4, the truncated episode 1 earns nothing, and data where no episode terminates are
    refused."""
    cfg = run_cfg(**{"finetune.rl_horizon": 3, "finetune.reward": "sparse"})
    batch = RLBuffers(cfg, episodes(), rl_horizon=3, seed=0).sample_offline()

    def at(e, t, key):
        rows = ((batch["episode"] == e) & (batch["step"] == t)).nonzero().squeeze(1)
        assert rows.numel(), f"window at episode {e}, t={t} not drawn"
        return batch[key][rows]

    for t, expected in ((0, 0.0), (1, 0.0), (2, 0.81)):
        value = at(0, t, ("next", "reward"))
        torch.testing.assert_close(value, torch.full_like(value, expected))
    mc = at(0, 0, ("mc", "return"))
    torch.testing.assert_close(mc, torch.full_like(mc, 0.9**4))
    assert float(batch["next", "reward"][batch["episode"] == 1].abs().max()) == 0.0
    shaped = FlowQTrainer(bc_actor(), cfg.finetune).shape_rewards(batch)
    rows = ((shaped["episode"] == 0) & (shaped["step"] == 2)).nonzero().squeeze(1)
    value = shaped["next", "reward"][rows]
    torch.testing.assert_close(value, torch.full_like(value, -0.01 - 0.9 * 0.01 + 0.81 * 0.0))

    with pytest.raises(ValueError, match=r"finetune.reward=sparse.*never true"):
        RLBuffers(cfg, episodes(terminated=(False, False)), rl_horizon=3, seed=0)


@pytest.mark.parametrize("mixing", ["seed", "balanced"])
def test_online_episodes_join_the_demonstrations(mixing):
    cfg = run_cfg(
        **{
            "online.mixing": mixing,
            "online.offline_fraction": 0.25,
            "online.steps": 40,
            "online.frames_per_round": 20,
        }
    )
    cfg.finetune.batch_size = 64
    buffers = RLBuffers(cfg, episodes(), rl_horizon=K, seed=0)
    offline = buffers.sample_offline()
    assert (offline["observation"][..., 0] < 200).all()  # demonstrations only
    online = episodes(lengths=(20, 20), terminated=(False, True), episode_offset=7)
    stored = buffers.add_collected(online)
    assert stored == 40 and buffers.online_steps_stored == 40
    batch = buffers.sample_online()
    assert batch.shape == (64,)
    from_online = (batch["observation"][:, -1, 0] >= 700).sum()
    if mixing == "balanced":
        assert from_online == 48  # exactly 1 - offline_fraction of every batch
    else:
        assert 0 < from_online < 64  # one pool: 40 online steps beside 17 demonstration steps
    assert torch.isfinite(batch["next", "reward"]).all() and batch["chunk_valid"].dtype == torch.bool


@pytest.mark.parametrize("mode", ["distill", "direct"])
def test_trainer_updates_the_actor_and_critics_and_leaves_the_bc_actor(mode):
    torch.manual_seed(0)
    cfg = run_cfg(**{"finetune.mode": mode, "finetune.alpha": 1.0, "finetune.batch_size": 32})
    bc = bc_actor()
    before = {k: v.clone() for k, v in bc.state_dict().items()}
    trainer = FlowQTrainer(bc, cfg.finetune)
    assert trainer.actor.sampler.nfe == (1 if mode == "distill" else 2)
    buffers = RLBuffers(cfg, episodes(), rl_horizon=K, seed=0)
    actor0 = {k: v.clone() for k, v in trainer.actor.state_dict().items()}
    critic0 = trainer.loss.qvalue_network_params.clone()
    target0 = trainer.loss.target_qvalue_network_params.clone()
    for _ in range(3):
        metrics = trainer.update(buffers.sample_offline())
    assert {"loss_actor", "loss_qvalue", "q_mean", "bc_loss", "lambda", "grad_norm"} <= set(metrics)
    assert any(not torch.equal(v, actor0[k]) for k, v in trainer.actor.state_dict().items())
    moved = trainer.loss.qvalue_network_params.get(("module", "mlp", "0", "weight"))
    assert not torch.equal(moved, critic0.get(("module", "mlp", "0", "weight")))
    tgt = trainer.loss.target_qvalue_network_params.get(("module", "mlp", "0", "weight"))
    assert not torch.equal(tgt, target0.get(("module", "mlp", "0", "weight")))  # Polyak-averaged
    assert all(torch.equal(v, before[k]) for k, v in bc.state_dict().items())
    assert trainer.bc_distance(buffers.sample_offline(), generator=torch.Generator().manual_seed(0)) > 0
    policy_cfg = finetuned_policy_config(
        {"name": "l1flow", "sampler": "two_step", "sampler_kwargs": {}}, mode
    )
    assert policy_cfg["sampler"] == ("euler" if mode == "distill" else "two_step")


@pytest.mark.parametrize("mode", ["distill", "direct"])
def test_critic_warmup_updates_move_the_critics_only(mode):
    torch.manual_seed(0)
    cfg = run_cfg(**{"finetune.mode": mode, "finetune.alpha": 1.0, "finetune.batch_size": 32})
    trainer = FlowQTrainer(bc_actor(), cfg.finetune)
    buffers = RLBuffers(cfg, episodes(), rl_horizon=K, seed=0)
    actor0 = {k: v.clone() for k, v in trainer.actor.state_dict().items()}
    critic0 = trainer.loss.qvalue_network_params.clone()
    for _ in range(3):
        metrics = trainer.update(buffers.sample_offline(), actor=False)
    assert "loss_actor" not in metrics and {"loss_qvalue", "q_data_mean", "grad_norm"} <= set(metrics)
    assert all(torch.equal(v, actor0[k]) for k, v in trainer.actor.state_dict().items())
    moved = trainer.loss.qvalue_network_params.get(("module", "mlp", "0", "weight"))
    assert not torch.equal(moved, critic0.get(("module", "mlp", "0", "weight")))
    assert trainer.updates == 3
    trainer.update(buffers.sample_offline())  # then the actor moves too
    assert any(not torch.equal(v, actor0[k]) for k, v in trainer.actor.state_dict().items())


def test_monte_carlo_targets_by_hand():
    """Shaped rewards r - 1 (scale 1, offset -1), gamma 0.9: a terminated episode's value is its
    return to the end; a truncated one's adds its last shaped reward repeated forever."""
    cfg = run_cfg(**{"finetune.reward_scale": 1.0, "finetune.reward_offset": -1.0})
    trainer = FlowQTrainer(bc_actor(), cfg.finetune)
    batch = RLBuffers(cfg, episodes(), rl_horizon=K, seed=0).sample_offline()
    mc = trainer.mc_targets(batch).reshape(-1)
    lengths, terminated = {0: 5, 1: 12}, {0: True, 1: False}
    for i in range(batch.shape[0]):
        e, t = int(batch["episode"][i]), int(batch["step"][i])
        n = lengths[e]
        # reward 1 + s, shaped to s
        expected = sum(GAMMA**k * (t + k) for k in range(n - t))
        if not terminated[e]:
            expected += GAMMA ** (n - t) * (n - 1) / (1 - GAMMA)
        assert mc[i].item() == pytest.approx(expected, rel=1e-5)


@pytest.mark.parametrize("mode", ["distill", "direct"])
def test_monte_carlo_pretraining_fits_the_returns_and_moves_the_critics_only(mode):
    torch.manual_seed(0)
    small = {"finetune.reward_scale": 0.05, "finetune.reward_offset": 0.0}  # values of a few units
    cfg = run_cfg(**{"finetune.mode": mode, "finetune.batch_size": 64, "finetune.lr": 3e-3, **small})
    trainer = FlowQTrainer(bc_actor(), cfg.finetune)
    buffers = RLBuffers(cfg, episodes(), rl_horizon=K, seed=0)
    actor0 = {k: v.clone() for k, v in trainer.actor.state_dict().items()}
    target0 = trainer.loss.target_qvalue_network_params.clone()
    with pytest.raises(ValueError, match="actor=False"):
        trainer.update(buffers.sample_offline(), critic="mc")
    probe = buffers.sample_offline()
    before = trainer.critic_diagnostics(probe, generator=torch.Generator().manual_seed(0))
    losses = [
        trainer.update(buffers.sample_offline(), actor=False, critic="mc")["loss_qvalue"] for _ in range(150)
    ]
    after = trainer.critic_diagnostics(probe, generator=torch.Generator().manual_seed(0))
    assert sum(losses[-10:]) < 0.1 * sum(losses[:10])
    # the critics now follow the data's values: Q rises and falls with the Monte-Carlo value
    assert after["q_mc_corr"] > 0.9 and after["q_mc_corr"] > before["q_mc_corr"]
    assert after["q_state_std"] > before["q_state_std"] and after["q_chunk_std"] >= 0
    assert all(torch.equal(v, actor0[k]) for k, v in trainer.actor.state_dict().items())
    # no bootstrap yet: the target critics stay put until the pretraining hands over
    assert (trainer.loss.target_qvalue_network_params == target0).all()
    trainer.sync_target_critics()
    assert (trainer.loss.target_qvalue_network_params == trainer.loss.qvalue_network_params.detach()).all()


def test_best_of_n_critics_can_keep_regressing_onto_returns():
    """finetune.critic_target=mc: in best_of_n there is no actor to train, so the online loop's
    ordinary update (actor=True) takes critic='mc': the critics fit the returns, the policy network
    and the target critics (no bootstrap) stay as they were."""
    torch.manual_seed(0)
    small = {"finetune.reward_scale": 0.05, "finetune.reward_offset": 0.0}
    cfg = run_cfg(
        **{"finetune.mode": "best_of_n", "finetune.num_samples": 2, "finetune.critic_target": "mc"},
        **{"finetune.batch_size": 64, "finetune.lr": 3e-3, **small},
    )
    trainer = FlowQTrainer(bc_actor(), cfg.finetune)
    buffers = RLBuffers(cfg, episodes(), rl_horizon=K, seed=0)
    actor0 = {k: v.clone() for k, v in trainer.actor.state_dict().items()}
    target0 = trainer.loss.target_qvalue_network_params.clone()
    losses = [trainer.update(buffers.sample_offline(), critic="mc")["loss_qvalue"] for _ in range(150)]
    assert sum(losses[-10:]) < 0.1 * sum(losses[:10])
    assert all(torch.equal(v, actor0[k]) for k, v in trainer.actor.state_dict().items())
    assert (trainer.loss.target_qvalue_network_params == target0).all()


def test_best_of_n_can_select_with_the_polyak_average_of_its_critics():
    """finetune.select_with=target: the executed chunk is picked by the target critics, which follow
    the Monte-Carlo-regressed critics by Polyak averaging (tau per update) instead of staying put."""
    torch.manual_seed(0)
    tau = 0.1
    cfg = run_cfg(
        **{"finetune.mode": "best_of_n", "finetune.num_samples": 4, "finetune.critic_target": "mc"},
        **{"finetune.select_with": "target", "finetune.tau": tau, "finetune.batch_size": 64},
    )
    trainer = FlowQTrainer(bc_actor(), cfg.finetune)
    buffers = RLBuffers(cfg, episodes(), rl_horizon=K, seed=0)
    target = trainer.loss.target_qvalue_network_params
    online = trainer.loss.qvalue_network_params
    weights = [k for k, v in target.items(True, True) if v.is_floating_point()]  # not the normalisers' ids
    expected = {k: target.get(k).detach().clone() for k in weights}
    for _ in range(5):
        trainer.update(buffers.sample_offline(), critic="mc")
        expected = {k: (1 - tau) * v + tau * online.get(k).detach() for k, v in expected.items()}
    assert all(torch.allclose(target.get(k), expected[k], atol=1e-6) for k in weights)
    assert not (target == trainer.loss.qvalue_network_params.detach()).all()
    # the acting (and saved) actor scores draws with those averaged critics
    selecting = trainer.policy_actor.critic_params
    assert all(
        a.data_ptr() == b.data_ptr() for a, b in zip(selecting.values(True, True), target.values(True, True))
    )
    saved = {k: v for k, v in trainer.policy_actor.state_dict().items() if k.startswith("critic_params.")}
    assert saved and all(torch.equal(v, selecting.get(tuple(k.split(".")[1:]))) for k, v in saved.items())
    # the default selects with the critics being trained, and Monte-Carlo updates leave the targets
    plain = FlowQTrainer(
        bc_actor(), run_cfg(**{"finetune.mode": "best_of_n", "finetune.critic_target": "mc"}).finetune
    )
    target0 = plain.loss.target_qvalue_network_params.clone()
    plain.update(buffers.sample_offline(), critic="mc")
    assert (plain.loss.target_qvalue_network_params == target0).all()
    assert plain.policy_actor.critic_params is plain.loss.qvalue_network_params


def test_bad_mixing_and_mode_are_named():
    with pytest.raises(ValueError, match=r"online\.mixing='half'"):
        RLBuffers(run_cfg(**{"online.mixing": "half"}), episodes(), rl_horizon=K, seed=0)
    with pytest.raises(ValueError, match=r"finetune\.mode='fql'"):
        FlowQTrainer(bc_actor(), run_cfg(**{"finetune.mode": "fql"}).finetune)


def test_bad_finetune_settings_fail_at_config_time(capsys):
    from l1flow_rl.cli import main

    code = main(
        [
            "finetune",
            "checkpoint=missing.pt",
            "finetune.mode=fql",
            "online.mixing=half",
            "online.steps=100",
            "online.num_envs=3",
            "online.frames_per_round=10",
            "offline.steps=10",
            "offline.critic_warmup=20",
            "finetune.backup=min",
            "finetune.backup_samples=-1",
            "finetune.critic_input=residual",
            "finetune.reward=dense",
            "finetune.critic_target=mc",
            "finetune.select_with=target",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2
    assert "finetune.mode='fql': expected one of ['best_of_n', 'direct', 'distill']" in err
    assert "online.mixing='half'" in err and "online.frames_per_round=10" in err
    assert "offline.critic_pretrain=0 + offline.critic_warmup=20: expected two counts >= 0" in err
    assert "summing to at most offline.steps=10" in err
    assert "finetune.backup='min': expected one of ['max', 'mean', 'one_step']" in err
    assert "finetune.backup_samples=-1: expected chunks drawn per TD target >= 1" in err
    assert "finetune.critic_input=residual needs finetune.mode=best_of_n" in err
    assert "finetune.reward='dense': expected one of ['recorded', 'sparse']" in err
    assert "finetune.critic_target=mc needs finetune.mode=best_of_n" in err
    assert "finetune.select_with=target needs finetune.mode=best_of_n" in err
    code = main(["finetune", "checkpoint=missing.pt", "online.steps=100", "online.frames_per_round=200"])
    err = capsys.readouterr().err
    assert code == 2 and "online.frames_per_round=200 gives each of online.num_envs=2 envs 100 steps" in err
    assert "fewer than task.max_episode_steps=150" in err and "use at least 300" in err


def test_a_run_made_before_a_setting_existed_resumes_only_under_its_old_behaviour(tmp_path):
    from l1flow_rl.workspace.checkpoint import CheckpointMismatchError
    from l1flow_rl.workspace.finetune import _check_resume

    current = OmegaConf.to_container(run_cfg(**{"finetune.mode": "best_of_n"}), resolve=True)
    saved = copy.deepcopy(current)
    for field in ("select_with", "critic_target"):  # a checkpoint from before these fields
        del saved["finetune"][field]
    _check_resume(saved, current, tmp_path / "latest.pt")  # the defaults behave as it did
    current["finetune"]["select_with"] = "target"
    with pytest.raises(CheckpointMismatchError, match=r"finetune\.select_with: checkpoint has 'critic'"):
        _check_resume(saved, current, tmp_path / "latest.pt")
