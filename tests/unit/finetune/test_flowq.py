"""flow-Q: the 2-NFE L1 Flow sampler as its own actor. Its gradient goes through both network calls
and never reaches the frozen teacher; at step 0 it samples exactly the BC policy's chunk; its preset
composes and validates; a run goes end to end through ``l1flow-rl finetune`` on the point-mass double
and resumes exactly when killed mid-way."""

from __future__ import annotations

import copy
import os
import signal

import pytest
import torch
from doubles.point_mass import TASK_OVERRIDES, TINY_BC
from omegaconf import OmegaConf
from tensordict import TensorDict

from l1flow_rl import FlowQLoss, L1FlowActor
from l1flow_rl.commands.cli import compose_config, main
from l1flow_rl.config.finetune import FinetuneConfig
from l1flow_rl.config.validate import ConfigValidationError
from l1flow_rl.finetune.base import Learner
from l1flow_rl.finetune.registry import get_algorithm
from l1flow_rl.workspace.checkpoint import load_actor, load_checkpoint


def small_flow() -> L1FlowActor:
    return L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))


def transitions(n: int = 8) -> TensorDict:
    return TensorDict(
        {
            "observation": torch.randn(n, 2, 5),
            "action_chunk": torch.rand(n, 16, 2) * 2 - 1,
            "next": {
                "observation": torch.randn(n, 2, 5),
                "reward": torch.rand(n, 1),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
            },
        },
        [n],
    )


def learner(flow: L1FlowActor, **finetune) -> Learner:
    cfg = OmegaConf.create(
        {**OmegaConf.to_container(OmegaConf.structured(FinetuneConfig(algorithm="flowq"))), **finetune}
    )
    cfg.critic_hidden_dims = [32]
    return Learner(get_algorithm("flowq"), flow, cfg)


def test_the_actor_gradient_passes_through_both_nfes_and_the_teacher_stays_as_it_was():
    torch.manual_seed(0)
    flow = small_flow()
    run = learner(flow)
    loss = run.loss
    assert isinstance(loss, FlowQLoss) and loss.actor is flow and loss.flow is loss.teacher
    teacher_before = copy.deepcopy(loss.teacher.state_dict())
    # every network output of the actor's sampler that is in the graph, with the gradient it receives
    outputs, real_denoise = [], flow.policy.denoise

    def recording_denoise(x, t, cond):
        out = real_denoise(x, t, cond)
        if out.requires_grad:
            record = {"t": float(t.flatten()[0]), "grad": None}
            out.register_hook(lambda g: record.__setitem__("grad", g))
            outputs.append(record)
        return out

    flow.policy.denoise = recording_denoise
    out = loss(transitions())
    out["loss_actor"].backward()
    # the actor loss holds both NFEs of the 2-NFE sampler (t = 0 and t = 0.5), and each gets a gradient
    assert [o["t"] for o in outputs] == [0.0, 0.5]
    assert all(o["grad"] is not None and o["grad"].abs().sum() > 0 for o in outputs)
    assert all(p.grad is None for p in loss.teacher.parameters())  # sampled without a graph
    assert all(p.grad is None for p in loss.critic.parameters())  # the critics' parameters detached
    del flow.policy.denoise
    # one optimiser step: the actor moves, the teacher (frozen, outside the optimiser) does not
    actor_before = copy.deepcopy(flow.state_dict())
    run.update(transitions())
    assert any(not torch.equal(v, actor_before[k]) for k, v in flow.state_dict().items())
    assert all(torch.equal(v, teacher_before[k]) for k, v in loss.teacher.state_dict().items())
    trained = {id(p) for group in run.optimizer.param_groups for p in group["params"]}
    assert trained.isdisjoint(id(p) for p in loss.teacher.parameters())
    assert {id(p) for p in flow.parameters()} <= trained


@pytest.mark.parametrize("ema_power", [0.0, 0.75])
def test_at_step_0_the_actor_samples_exactly_the_bc_policys_chunk_for_the_same_noise(ema_power):
    torch.manual_seed(0)
    bc = small_flow()
    run = learner(copy.deepcopy(bc), ema_power=ema_power)
    obs, z = torch.randn(6, 2, 5), torch.randn(6, 16, 2)
    expected = bc.policy.sample_chunk(obs, noise=z)
    for acting in (run.loss.actor, run.acting, run.start):
        assert torch.equal(acting.policy.sample_chunk(obs, noise=z), expected)
    # and the anchor starts at zero: the actor's first step moves it by the Q term alone
    out = run.loss(transitions())
    assert out["teacher_distance"].item() == 0.0 and out["anchor_loss"].item() == 0.0


def test_lambda_is_floored_while_the_critics_sit_near_zero():
    loss = learner(small_flow()).loss
    assert loss.q_weight(torch.full((4,), 1e-4)).item() == pytest.approx(1 / 0.1)  # FQL's: 1e4
    assert loss.q_weight(torch.tensor([0.5, -1.5])).item() == pytest.approx(1.0)  # FQL's 1 / mean|Q|


def test_the_data_anchor_is_the_flows_l1_flow_loss():
    run = learner(small_flow(), flowq={"bc_on_data": True})
    out = run.loss(transitions())
    assert out["anchor_loss"].item() > 0 and out["teacher_distance"].item() == 0.0
    assert run.loss.bc_loss is not None and run.loss.bc_loss.actor_network is run.loss.actor


def test_the_preset_composes_validates_and_builds_its_loss():
    cfg = compose_config(["finetune=flowq", "checkpoint=bc.pt"], command="finetune")
    assert cfg.finetune.algorithm == "flowq" and cfg.finetune.q_agg == "mean"
    assert OmegaConf.to_container(cfg.finetune.flowq) == {
        "alpha": 10.0,
        "normalize_q_loss": True,
        "q_scale_floor": 0.1,
        "bc_on_data": False,
    }
    assert cfg.online.offline_fraction == 0.5 and cfg.online.updates_per_step == 0.5
    assert cfg.offline.steps == 10000 and cfg.offline.critic_only is True and cfg.offline.eval_every == 0
    small = OmegaConf.merge(cfg.finetune, {"critic_hidden_dims": [16]})
    loss = get_algorithm("flowq").build(small_flow(), small)
    assert isinstance(loss, FlowQLoss) and loss.critic.num_critics == cfg.finetune.num_critics
    bad = [
        ("finetune.flowq.q_scale_floor=0", r"finetune\.flowq\.q_scale_floor=0\.0: expected > 0"),
        ("finetune.flowq.alpha=-1", r"finetune\.flowq\.alpha=-1\.0: expected >= 0"),
        ("finetune.flowq.bc_on_data=maybe", r"finetune\.flowq\.bc_on_data='maybe': expected bool"),
        ("+finetune.flowq.alfa=1", r"finetune\.flowq\.alfa: not a setting of flowq"),
    ]
    for override, says in bad:
        with pytest.raises(ConfigValidationError, match=says):
            compose_config(["finetune=flowq", "checkpoint=bc.pt", override], command="finetune")


def test_a_critic_only_update_moves_the_critics_and_leaves_the_actor_and_its_ema_at_the_start():
    run = learner(small_flow(), ema_power=0.75)
    actor = {k: v.clone() for k, v in run.loss.actor.state_dict().items()}
    ema = {k: v.clone() for k, v in run.acting.state_dict().items()}
    critic = [p.detach().clone() for p in run.loss.critic.parameters()]
    out = run.update(transitions(), critic_only=True)
    assert sorted(k for k in out if k.startswith("loss_")) == ["loss_qvalue"]
    assert all(torch.equal(v, run.loss.actor.state_dict()[k]) for k, v in actor.items())
    assert all(torch.equal(v, run.acting.state_dict()[k]) for k, v in ema.items())
    assert any(not torch.equal(a, b) for a, b in zip(critic, run.loss.critic.parameters(), strict=True))
    run.update(transitions())  # the full update moves the actor
    assert any(not torch.equal(v, run.loss.actor.state_dict()[k]) for k, v in actor.items())


@pytest.mark.parametrize(
    "preset, ok", [("flowq", True), ("qc", True), ("fql", False), ("filtered_bc", False)]
)
def test_critic_only_offline_is_refused_where_the_actor_must_learn_offline_or_there_is_no_critic(preset, ok):
    args = [f"finetune={preset}", "checkpoint=bc.pt", "offline.critic_only=true"]
    if ok:
        assert compose_config(args, command="finetune").offline.critic_only is True
    else:
        with pytest.raises(
            ConfigValidationError, match=f"offline.critic_only=true: finetune.algorithm={preset}"
        ):
            compose_config(args, command="finetune")


# -- end to end on the point-mass double -------------------------------------------------------------

# 3 offline updates (checkpointed at the phase's end), then 2 rounds of 60 env steps (2 envs) with no
# warm-up, each followed by 0.05 x 60 = 3 updates and a checkpoint: 3 + 6 updates
FINETUNE = [
    *TASK_OVERRIDES,
    "finetune=flowq",
    "offline.steps=3",
    "online.steps=120",
    "online.warmup_steps=0",
    "online.num_envs=2",
    "online.frames_per_round=60",
    "online.updates_per_step=0.05",
    "online.checkpoint_every=60",
    "finetune.batch_size=16",
    "finetune.critic_hidden_dims=[32,32]",
    "eval.num_envs=1",
    "device=cpu",
]


@pytest.fixture(scope="module")
def bc_checkpoint(tmp_path_factory):
    data_dir, run_dir = tmp_path_factory.mktemp("demos"), tmp_path_factory.mktemp("bc") / "run"
    assert main([*TINY_BC, f"data_dir={data_dir}", f"run_dir={run_dir}"]) == 0
    return data_dir, run_dir / "checkpoints" / "latest.pt"


def _args(run_dir, bc_checkpoint, *extra):
    data_dir, checkpoint = bc_checkpoint
    return [
        "finetune",
        f"checkpoint={checkpoint}",
        f"data_dir={data_dir}",
        f"run_dir={run_dir}",
        *FINETUNE,
        *extra,
    ]


def _differing(a: dict, b: dict) -> list[str]:
    return [k for k in a if isinstance(a[k], torch.Tensor) and not torch.equal(a[k], b[k])]


def test_a_flowq_run_goes_end_to_end_and_resumes_exactly_when_killed_mid_way(
    tmp_path, bc_checkpoint, monkeypatch
):
    straight_dir = tmp_path / "straight"
    assert main(_args(straight_dir, bc_checkpoint, "eval.enabled=false")) == 0
    straight = load_checkpoint(straight_dir / "checkpoints" / "latest.pt")
    assert straight["progress"] == {
        "offline_updates": 3,
        "online_updates": 6,
        "env_steps": 120,
        "rounds": 2,
        "started": True,
    }
    assert straight["config"]["policy"]["finetune"]["flowq"]["alpha"] == 10.0
    actor, _ = load_actor(straight_dir / "checkpoints" / "latest.pt")
    assert isinstance(actor, L1FlowActor)  # the trained flow acts, and l1flow-rl eval rebuilds it
    bc = load_checkpoint(bc_checkpoint[1])
    assert any(not torch.equal(v, bc["ema"][k]) for k, v in straight["model"].items())  # the actor moved
    teacher = {k[len("teacher.") :]: v for k, v in straight["loss"].items() if k.startswith("teacher.")}
    assert teacher and all(torch.equal(v, bc["ema"][k]) for k, v in teacher.items())  # frozen at BC

    # killed at the second update of the second round; the last checkpoint is the first round's
    run_dir = tmp_path / "run"
    args = _args(run_dir, bc_checkpoint, "eval.enabled=false")
    real_update, calls = Learner.update, {"n": 0}

    def crashing_update(self, batch, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3 + 3 + 2:
            raise RuntimeError("simulated kill")
        return real_update(self, batch, **kwargs)

    monkeypatch.setattr(Learner, "update", crashing_update)
    with pytest.raises(RuntimeError, match="simulated kill"):
        main(args)
    assert load_checkpoint(run_dir / "checkpoints" / "latest.pt")["progress"]["env_steps"] == 60
    monkeypatch.setattr(Learner, "update", real_update)
    assert main([*args, "resume=true"]) == 0
    resumed = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert resumed["progress"] == straight["progress"]
    for key in ("model", "loss", "buffers"):
        assert _differing(resumed[key], straight[key]) == [], key
    assert resumed["optimizer"]["state"].keys() == straight["optimizer"]["state"].keys()
    for k, state in straight["optimizer"]["state"].items():
        assert all(torch.equal(v, resumed["optimizer"]["state"][k][n]) for n, v in state.items())
    strip = lambda rows: [{k: v for k, v in r.items() if not k.endswith("_per_s")} for r in rows]  # noqa: E731
    assert strip(resumed["records"]["rounds"]) == strip(straight["records"]["rounds"])


def test_a_stop_signal_between_checkpoints_saves_the_online_buffer_with_the_weights(
    tmp_path, bc_checkpoint, monkeypatch
):
    # 3 rounds, checkpointed only at the end; SIGTERM in round 2's updates: the signal's latest.pt
    # is the only one, and it must name a buffer dump holding both rounds (before: it named none, so
    # the resumed run sampled from an empty online buffer)
    def args(run_dir):
        return _args(
            run_dir, bc_checkpoint, "eval.enabled=false", "online.steps=180", "online.checkpoint_every=0"
        )

    assert main(args(tmp_path / "straight")) == 0
    straight = load_checkpoint(tmp_path / "straight" / "checkpoints" / "latest.pt")
    real_update, calls = Learner.update, {"n": 0}

    def signalled_update(self, batch, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3 + 3 + 1:  # 3 offline updates, 3 in round 1, the first of round 2
            os.kill(os.getpid(), signal.SIGTERM)  # the harness checkpoints after this round
        return real_update(self, batch, **kwargs)

    monkeypatch.setattr(Learner, "update", signalled_update)
    assert main(args(tmp_path / "run")) == 128 + signal.SIGTERM
    monkeypatch.setattr(Learner, "update", real_update)
    stopped = load_checkpoint(tmp_path / "run" / "checkpoints" / "latest.pt")
    assert stopped["progress"]["env_steps"] == 120 and stopped["progress"]["rounds"] == 2
    assert stopped["online_buffer"] == "online_buffer_round2"
    assert main([*args(tmp_path / "run"), "resume=true"]) == 0
    resumed = load_checkpoint(tmp_path / "run" / "checkpoints" / "latest.pt")
    assert resumed["progress"] == straight["progress"]
    for key in ("model", "loss", "buffers"):
        assert _differing(resumed[key], straight[key]) == [], key
    dumps = sorted(p.name for p in (tmp_path / "run" / "checkpoints").glob("online_buffer_round*"))
    assert dumps == ["online_buffer_round3"]  # the signal's dump went once latest.pt named another


def test_a_relaunched_grid_skips_a_finished_flowq_run_and_refuses_one_of_another_setting(
    tmp_path, bc_checkpoint, capsys
):
    run_dir = tmp_path / "grid" / "flowq" / "seed0"
    args = _args(run_dir, bc_checkpoint, "eval.enabled=false", "resume=auto")
    assert main(args) == 0
    latest = run_dir / "checkpoints" / "latest.pt"
    written = latest.stat().st_mtime_ns, (run_dir / "summary.json").read_bytes()
    capsys.readouterr()
    assert main(args) == 0  # the same job again: nothing is trained, nothing rewritten
    assert "holds this run, finished (summary.json); skipped (resume=auto)" in capsys.readouterr().out
    assert (latest.stat().st_mtime_ns, (run_dir / "summary.json").read_bytes()) == written
    assert main([*args, "finetune.flowq.alpha=30"]) != 0  # another setting: an error, not its figure
    assert "finetune.flowq.alpha: the finished run has 10.0, config asks for 30.0" in capsys.readouterr().err
    assert latest.stat().st_mtime_ns == written[0]
