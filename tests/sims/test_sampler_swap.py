"""Re-scoring one trained network under another sampler: the Python API (shared weights, counted
network evaluations, refusals that list the samplers that fit) and ``l1flow-rl eval`` with
``policy.sampler=...`` on a real ManiSkill env."""

from __future__ import annotations

import json

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict

from l1flow_rl import DiffusionLoss, L1FlowActor, L1FlowLoss
from l1flow_rl.evaluation.rescore import eval_sampler
from l1flow_rl.flow.samplers import DDIMSampler, DDPMSampler, SamplerMismatchError, samplers_for

OBS, ACT = 35, 4  # ManiSkill PushCube state and pd_ee_delta_pos action


def count_calls(actor: L1FlowActor) -> list[int]:
    calls = [0]
    actor.policy.net.register_forward_hook(lambda *_: calls.__setitem__(0, calls[0] + 1))
    return calls


def obs(batch: int = 3) -> TensorDict:
    return TensorDict({"observation": torch.randn(batch, 2, OBS)}, batch_size=[batch])


def tiny_actor(sampler=None) -> L1FlowActor:
    kwargs = {"sampler": sampler} if sampler is not None else {}
    return L1FlowActor.for_state(OBS, ACT, down_dims=(16, 32), timestep_embed_dim=16, **kwargs)


def train_a_few_steps(actor: L1FlowActor, loss_cls, steps: int = 5) -> None:
    loss_fn = loss_cls(actor)
    optim = torch.optim.Adam(actor.parameters(), lr=1e-3)
    gen = torch.Generator().manual_seed(0)
    for _ in range(steps):
        td = TensorDict(
            {
                "observation": torch.randn(16, 2, OBS, generator=gen),
                "action_chunk": torch.rand(16, 16, ACT, generator=gen) * 2 - 1,
            },
            batch_size=[16],
        )
        optim.zero_grad()
        loss_fn(td)[loss_fn.loss_name].backward()
        optim.step()


def test_swapped_actor_shares_the_network_and_counts_its_own_nfe():
    ddpm = tiny_actor(DDPMSampler(num_train_timesteps=20))
    ddim = ddpm.with_sampler("ddim", steps=5, num_train_timesteps=20)
    assert ddim.policy.net is ddpm.policy.net
    assert ddim.policy.action_normalizer is ddpm.policy.action_normalizer
    assert isinstance(ddpm.sampler, DDPMSampler) and isinstance(ddim.sampler, DDIMSampler)
    calls = count_calls(ddpm)  # the hook sits on the shared network
    ddim(obs())
    assert calls[0] == 5
    ddpm(obs())
    assert calls[0] == 5 + 20
    # a change to the weights shows through both actors
    with torch.no_grad():
        next(ddpm.policy.net.parameters()).add_(1.0)
    assert torch.equal(next(ddim.parameters()), next(ddpm.parameters()))


def test_l1flow_network_under_euler_and_another_t_first():
    actor = tiny_actor()
    calls = count_calls(actor)
    euler = actor.with_sampler("euler", steps=4)
    euler(obs())
    assert calls[0] == 4
    other = actor.with_sampler("two_step", t_first=0.3)
    other(obs())
    assert calls[0] == 6 and other.sampler.t_first == 0.3 and actor.sampler.t_first == 0.5
    actor.set_sampler("euler", steps=3)  # in place
    actor(obs())
    assert calls[0] == 9 and actor.sampler.nfe == 3


@pytest.mark.parametrize(
    ("trained", "wrong", "fit"),
    [
        (None, DDIMSampler(16), ["euler", "two_step"]),  # L1 Flow (sample prediction) under DDIM
        (DDPMSampler(), "velocity_euler", ["ddim", "ddpm"]),
    ],
)
def test_a_sampler_for_another_prediction_type_is_refused(trained, wrong, fit):
    actor = tiny_actor(trained)
    with pytest.raises(SamplerMismatchError, match=rf"samplers that fit: {fit!r}".replace("[", r"\[")):
        actor.with_sampler(wrong)
    with pytest.raises(SamplerMismatchError):
        actor.set_sampler(wrong)
    assert samplers_for(actor.sampler.prediction) == fit  # the actor itself is unchanged


def test_ddim_on_another_training_schedule_and_unknown_kwargs_are_refused():
    actor = tiny_actor(DDPMSampler(num_train_timesteps=100))
    with pytest.raises(SamplerMismatchError, match=r"num_train_timesteps=50 \(trained with 100\)"):
        actor.with_sampler("ddim", steps=10, num_train_timesteps=50)
    with pytest.raises(ValueError, match=r"sampler 'ddim' takes no argument \['t_first'\]"):
        actor.with_sampler("ddim", t_first=0.5)
    l1flow = L1FlowActor.for_state(OBS, ACT, down_dims=(16, 32))  # sample prediction
    with pytest.raises(SamplerMismatchError, match=r"samplers that fit: \['euler', 'two_step'\]"):
        l1flow.with_sampler("direct")  # regression reads another target


def test_eval_sampler_applies_only_what_the_command_line_gives():
    saved = {"sampler": "ddpm", "sampler_kwargs": {"num_train_timesteps": 50}}
    # the composed config comes from the default policy file (l1flow) plus the user's overrides
    composed = {"sampler": "ddim", "sampler_kwargs": {"t_first": 0.5, "steps": 16}}
    given = ["policy.sampler=ddim", "++policy.sampler_kwargs.steps=16", "eval.episodes=3"]
    assert eval_sampler(saved, composed, given) == ("ddim", {"num_train_timesteps": 50, "steps": 16})
    assert eval_sampler(saved, composed, ["eval.episodes=3"]) == ("ddpm", {"num_train_timesteps": 50})
    l1 = {"sampler": "two_step", "sampler_kwargs": {"t_first": 0.5}}
    assert eval_sampler(
        l1, {"sampler": "two_step", "sampler_kwargs": {"t_first": 0.3}}, ["policy.sampler_kwargs.t_first=0.3"]
    ) == ("two_step", {"t_first": 0.3})
    # policy=NAME: that file's sampler settings
    ddim_file = {"sampler": "ddim", "sampler_kwargs": {"steps": 16, "num_train_timesteps": 100}}
    assert eval_sampler(saved, ddim_file, ["policy=ddim"]) == ("ddim", ddim_file["sampler_kwargs"])
    with pytest.raises(ValueError, match=r"not \['policy.down_dims'\]"):
        eval_sampler(saved, composed, ["policy.down_dims=[8,16]"])


# -- l1flow-rl eval on the real simulator ------------------------------------------------------------


def save_tiny_checkpoint(tmp_path, policy: str, loss_cls):
    from l1flow_rl.commands.cli import compose_config
    from l1flow_rl.workspace.build import build_actor
    from l1flow_rl.workspace.checkpoint import save_checkpoint

    overrides = [f"policy={policy}", "network.down_dims=[16,32]", "network.timestep_embed_dim=16"]
    if policy == "ddpm":
        overrides.append("policy.sampler_kwargs.num_train_timesteps=32")
    cfg = compose_config(overrides)
    actor = build_actor(cfg.policy, {"state": (OBS,)}, ACT, None, cfg.network)
    train_a_few_steps(actor, loss_cls)
    return save_checkpoint(
        tmp_path / f"{policy}.pt",
        {
            "model": actor.state_dict(),
            "ema": None,
            "config": OmegaConf.to_container(cfg, resolve=True),
            "obs_shapes": {"state": [OBS]},
            "action_dim": ACT,
        },
    )


def run_eval_cli(tmp_path, checkpoint, *overrides) -> dict:
    from l1flow_rl.commands.cli import main

    run_dir = tmp_path / f"eval_{len(list(tmp_path.iterdir()))}"
    args = [f"checkpoint={checkpoint}", f"run_dir={run_dir}", "device=cpu", "eval.episodes=1"]
    args += ["eval.num_envs=1", "task.max_episode_steps=8", *overrides]  # 8 steps: exactly one chunk
    assert main(["eval", *args]) == 0
    return json.loads((run_dir / "eval.json").read_text())


@pytest.mark.maniskill
def test_cli_rescores_a_ddpm_network_under_ddim16_and_l1flow_under_euler4(tmp_path):
    pytest.importorskip("mani_skill")
    ddpm = save_tiny_checkpoint(tmp_path, "ddpm", DiffusionLoss)
    result = run_eval_cli(tmp_path, ddpm, "policy.sampler=ddim", "policy.sampler_kwargs.steps=16")
    assert result["sampler"]["name"] == "ddim" and result["sampler"]["nfe"] == 16
    assert result["sampler"]["kwargs"]["num_train_timesteps"] == 32  # the checkpoint's schedule carried over
    assert result["sampler"]["trained_with"]["name"] == "ddpm"
    assert (result["policy_calls"], result["network_calls"], result["nfe_per_chunk"]) == (1, 16, 16.0)

    l1flow = save_tiny_checkpoint(tmp_path, "l1flow", L1FlowLoss)
    result = run_eval_cli(tmp_path, l1flow, "policy.sampler=euler", "policy.sampler_kwargs.steps=4")
    assert result["sampler"]["name"] == "euler" and result["sampler"]["kwargs"] == {"steps": 4}
    assert (result["network_calls"], result["nfe_per_chunk"]) == (4, 4.0)
    assert result["per_episode"][0]["length"] == 8

    own = run_eval_cli(tmp_path, l1flow)  # no sampler given: the checkpoint's own
    assert own["sampler"]["name"] == "two_step" and own["nfe_per_chunk"] == 2.0

    with pytest.raises(SamplerMismatchError, match=r"samplers that fit: \['euler', 'two_step'\]"):
        run_eval_cli(tmp_path, l1flow, "policy.sampler=ddim", "policy.sampler_kwargs.steps=16")
