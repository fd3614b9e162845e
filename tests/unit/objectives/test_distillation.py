"""Consistency Policy and OneDP: students start from a frozen teacher and train while it stays fixed,
OneDP-S's score network learns on the generator's chunks, the teacher= checks refuse an unfit
checkpoint in one line before any work, and each policy trains, evaluates and keeps its ledger end to
end on the point-mass double."""

from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path

import pytest
import torch
from doubles.point_mass import TASK_OVERRIDES
from omegaconf import OmegaConf
from tensordict import TensorDict

from l1flow_rl import ConsistencyLoss, L1FlowActor, OneDPDLoss, OneDPSLoss
from l1flow_rl.commands.cli import compose_config, main
from l1flow_rl.config.validate import ConfigValidationError
from l1flow_rl.flow import (
    ConsistencySampler,
    DDPMSampler,
    EDMHeunSampler,
    OneStepDDPMSampler,
    OneStepEDMSampler,
)
from l1flow_rl.workspace.checkpoint import load_checkpoint, save_checkpoint
from l1flow_rl.workspace.trainer import Trainer

EDM_SCALE = 1000.0


def _actor(sampler, scale=EDM_SCALE):
    return L1FlowActor.for_state(
        obs_dim=5,
        action_dim=2,
        down_dims=(16, 32),
        timestep_embed_dim=16,
        sampler=sampler,
        timestep_scale=scale,
    )


def _batch(n=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "observation": torch.randn(n, 2, 5, generator=g),
            "action_chunk": torch.rand(n, 16, 2, generator=g) * 2 - 1,
        },
        batch_size=[n],
    )


def _net_state(actor):
    return {k: v.detach().clone() for k, v in actor.policy.net.state_dict().items()}


#: (loss, teacher sampler, student sampler, time scale): each student with each teacher it takes
STUDENTS = {
    "consistency": (ConsistencyLoss, EDMHeunSampler(4), ConsistencySampler(3), EDM_SCALE),
    "consistency_trajectory": (
        lambda actor, teacher: ConsistencyLoss(actor, teacher=teacher, trajectory=True),
        EDMHeunSampler(4),
        ConsistencySampler(3, trajectory=True),
        EDM_SCALE,
    ),
    "onedp_d_edm": (OneDPDLoss, EDMHeunSampler(4), OneStepEDMSampler(stochastic=False), EDM_SCALE),
    "onedp_d_ddpm": (OneDPDLoss, DDPMSampler(), OneStepDDPMSampler(stochastic=False), 1.0),
    "onedp_s_edm": (OneDPSLoss, EDMHeunSampler(4), OneStepEDMSampler(), EDM_SCALE),
    "onedp_s_ddpm": (OneDPSLoss, DDPMSampler(), OneStepDDPMSampler(), 1.0),
}


@pytest.mark.parametrize("name", sorted(STUDENTS))
def test_the_student_starts_from_the_teacher_and_trains_while_the_teacher_stays_fixed(name):
    torch.manual_seed(0)
    loss_cls, teacher_sampler, student_sampler, scale = STUDENTS[name]
    teacher, student = _actor(teacher_sampler, scale), _actor(student_sampler, scale)
    with torch.no_grad():  # a teacher whose normaliser is not the identity, so copying it shows
        teacher.policy.action_normalizer.scale.fill_(0.5)
    frozen = _net_state(teacher)
    assert any(not torch.equal(frozen[k], v) for k, v in _net_state(student).items())
    loss_fn = loss_cls(student, teacher=teacher)
    start = _net_state(student)
    assert all(torch.equal(start[k], frozen[k]) for k in frozen)  # the student starts as the teacher
    assert torch.equal(student.policy.action_normalizer.scale, teacher.policy.action_normalizer.scale)
    assert not any(p.requires_grad for p in teacher.parameters())

    trainer = Trainer(student, loss_fn, total_steps=3, lr=1e-3, warmup_steps=0)
    for step in range(3):
        metrics = trainer.train_step(_batch(seed=step))
        assert torch.isfinite(metrics["loss"])
    moved = [k for k, v in _net_state(student).items() if not torch.equal(v, start[k])]
    assert len(moved) > len(start) // 2, f"only {moved} moved"
    assert all(torch.equal(v, frozen[k]) for k, v in _net_state(teacher).items())
    assert all(p.grad is None for p in teacher.parameters())


def test_onedp_s_score_network_learns_on_the_generators_chunks_not_on_data():
    torch.manual_seed(0)
    teacher, student = _actor(EDMHeunSampler(4)), _actor(OneStepEDMSampler())
    loss_fn = OneDPSLoss(student, teacher=teacher)
    td = _batch()
    fed, generated = [], []
    view, sampler = loss_fn.teacher_view, student.policy.sampler
    real_error, real_generate = view.training_error, sampler.generate

    def spy_error(policy, cond, x0):
        fed.append((policy, x0.clone()))
        return real_error(policy, cond, x0)

    def spy_generate(denoise, z):
        out = real_generate(denoise, z)
        generated.append(out.detach().clone())
        return out

    view.training_error, sampler.generate = spy_error, spy_generate
    try:
        loss_fn(td)
    finally:
        del view.training_error, sampler.generate
    ((policy, x0),) = fed
    assert policy is loss_fn.score_network and not x0.requires_grad
    assert torch.equal(x0, generated[0])  # the generator's chunks ...
    assert not torch.allclose(x0, td["action_chunk"], atol=0.1)  # ... not the demonstrations

    # The score network is trained (its parameters are the loss's extra ones) and its error falls on a
    # fixed draw; the generator is not stepped here, so its chunks stay the same.
    score_params = loss_fn.extra_parameters()
    assert score_params and all(p.requires_grad for p in score_params)
    assert not {id(p) for p in score_params} & {id(p) for p in student.parameters()}
    before = [p.detach().clone() for p in score_params]
    optimizer = torch.optim.Adam(score_params, lr=1e-3)
    terms = []
    for _ in range(25):
        torch.manual_seed(1)
        out = loss_fn(td)
        terms.append(float(out["score_term"]))
        optimizer.zero_grad()
        out["loss_onedp"].backward()
        optimizer.step()
    assert terms[-1] < 0.7 * terms[0], terms
    assert any(not torch.equal(p, b) for p, b in zip(score_params, before, strict=True))


def test_a_generator_reads_its_network_as_the_teacher_does_at_its_fixed_level():
    # EDM: D(sigma_init z, sigma_init), so on the teacher's weights it is the teacher's one-step denoiser
    torch.manual_seed(0)
    z, out = torch.randn(3, 16, 2), torch.randn(3, 16, 2)
    seen = []

    def net(x, c):
        seen.append((x.clone(), c.clone()))
        return out

    got = OneStepEDMSampler(sigma_init=1.7).generate(net, z)
    c_skip, c_out, c_in, c_noise = EDMHeunSampler().preconditioning.scalings(torch.tensor(1.7))
    assert torch.allclose(got, c_skip * 1.7 * z + c_out * out)
    assert torch.allclose(seen[0][0], c_in * 1.7 * z) and torch.allclose(seen[0][1], c_noise.expand(3))
    # DDPM: the epsilon network at step t_init, x0 = (z - sqrt(1 - a) eps) / sqrt(a)
    ddpm = OneStepDDPMSampler(t_init=65)
    a = ddpm.schedule.alphas_cumprod[65]
    steps = []
    got = ddpm.generate(lambda x, t: steps.append(t) or out, z)
    assert torch.allclose(got, (z - (1 - a).sqrt() * out) / a.sqrt())
    assert steps[0].tolist() == [65.0] * 3


def test_onedp_s_score_network_resumes_from_the_checkpoint():
    teacher = _actor(EDMHeunSampler(4))
    loss_fn = OneDPSLoss(_actor(OneStepEDMSampler()), teacher=teacher)
    trainer = Trainer(loss_fn.actor_network, loss_fn, total_steps=2, lr=1e-2, warmup_steps=0)
    trainer.train_step(_batch())
    state = trainer.state_dict()
    assert set(state["loss_state"]) == {f"score_network.{k}" for k in loss_fn.score_network.state_dict()}
    other = OneDPSLoss(_actor(OneStepEDMSampler()), teacher=teacher)
    Trainer(other.actor_network, other, total_steps=2).load_state_dict(state)
    theirs = other.score_network.state_dict()
    assert all(torch.equal(theirs[k], v) for k, v in loss_fn.score_network.state_dict().items())
    assert not all(torch.equal(theirs[k], v) for k, v in teacher.policy.state_dict().items())


def test_onedp_d_reads_no_score_network_and_its_fake_side_is_the_generators_chunk():
    loss_fn = OneDPDLoss(_actor(OneStepEDMSampler(stochastic=False)), teacher=_actor(EDMHeunSampler(4)))
    assert loss_fn.extra_parameters() == [] and not hasattr(loss_fn, "score_network")
    out = loss_fn(_batch())
    assert set(out.keys()) == {"loss_onedp", "generator_term"}
    # deterministic: the generator's input is zeros, so two chunks of one observation agree
    obs = TensorDict({"observation": torch.randn(1, 2, 5).expand(2, 2, 5)}, batch_size=[2])
    chunk = loss_fn.actor_network(obs)["action_chunk"]
    assert torch.allclose(chunk[0], chunk[1], atol=1e-6)


def test_consistency_target_network_follows_the_student_by_its_decay_and_resumes():
    torch.manual_seed(0)
    teacher, student = _actor(EDMHeunSampler(4)), _actor(ConsistencySampler())
    loss_fn = ConsistencyLoss(student, teacher=teacher, target_decay=0.5)
    trainer = Trainer(student, loss_fn, total_steps=2, lr=1e-2, warmup_steps=0)
    trainer.train_step(_batch())
    target_before = {k: v.clone() for k, v in loss_fn.training_state().items()}
    live = {
        f"target.{k}": v.detach().clone() for k, v in loss_fn.actor_network_params.flatten_keys(".").items()
    }
    loss_fn.update_target()
    for key, value in loss_fn.training_state().items():
        if value.is_floating_point():
            assert torch.allclose(value, 0.5 * target_before[key] + 0.5 * live[key], atol=1e-6), key
    state = trainer.state_dict()
    assert set(state["loss_state"]) == set(target_before)
    # a fresh trainer restores the target network from the checkpoint
    other = ConsistencyLoss(_actor(ConsistencySampler()), teacher=teacher, target_decay=0.5)
    Trainer(other.actor_network, other, total_steps=2).load_state_dict(state)
    assert all(torch.equal(other.training_state()[k], v) for k, v in state["loss_state"].items())


@pytest.mark.parametrize("teacher_kind", ["edm", "ddpm"])
def test_onedps_generator_gradient_is_the_sigma_squared_weighted_score_difference(teacher_kind):
    # OneDP section 2.3: w(k) = sigma_k^2 (DreamFusion's), so the gradient on the generator's chunk A is
    # sigma^2 (s_fake - s_real) dx_k/dA: fake - real for EDM, alpha_bar_k (fake - real) for DDPM. The
    # deterministic generator's fake estimate is A itself. Here mean |A - real| = 0.3 per chunk, so a
    # per-chunk normaliser (DMD's) would scale the gradient by 1 / 0.3.
    torch.manual_seed(0)
    if teacher_kind == "edm":
        teacher_sampler, student_sampler, scale = EDMHeunSampler(4), OneStepEDMSampler(stochastic=False), 1e3
        level = torch.tensor([0.1, 0.5, 2.5, 10.0])
        weight = torch.ones(4, 1, 1)
    else:
        teacher_sampler, student_sampler, scale = DDPMSampler(), OneStepDDPMSampler(stochastic=False), 1.0
        level = torch.tensor([2, 30, 65, 95])
        weight = DDPMSampler().schedule.alpha_bar(level).float().reshape(4, 1, 1)
    loss_fn = OneDPDLoss(_actor(student_sampler, scale), teacher=_actor(teacher_sampler, scale))
    chunk = torch.randn(4, 16, 2, requires_grad=True)
    real = chunk.detach() - 0.3 * torch.randn(4, 16, 2).sign()
    view, sampler = loss_fn.teacher_view, loss_fn.policy.sampler
    view.distillation_levels = lambda n, device: level
    view.clean = lambda policy, cond, x, lv: real
    sampler.generate = lambda denoise, z: chunk
    try:
        out = loss_fn(_batch(4))
    finally:
        del view.distillation_levels, view.clean, sampler.generate
    (grad,) = torch.autograd.grad(out["loss_onedp"], chunk)
    assert torch.allclose(grad * chunk.numel(), weight * (chunk - real), atol=1e-6)


def test_onedp_draws_ddpm_steps_in_2_to_95_edm_levels_log_normal_and_starts_at_its_fixed_levels():
    from l1flow_rl.objectives.distillation import teacher_view

    torch.manual_seed(0)
    steps = teacher_view(DDPMSampler()).distillation_levels(20000, torch.device("cpu"))
    assert int(steps.min()) == 2 and int(steps.max()) == 95  # OneDP's Table 7 range, both ends drawn
    log_sigma = teacher_view(EDMHeunSampler()).distillation_levels(20000, torch.device("cpu")).log()
    assert abs(float(log_sigma.mean()) + 1.2) < 0.05 and abs(float(log_sigma.std()) - 1.2) < 0.05
    # the generator's fixed input level (OneDP's Table 7: sigma 2.5 for EDM, step 65 for DDPM)
    assert OneStepEDMSampler().sigma_init == 2.5 and OneStepDDPMSampler().t_init == 65


def test_onedp_trains_the_generator_at_1e6_and_its_score_network_20_times_faster_with_beta1_0():
    for policy in ("onedp_d", "onedp_s"):
        cfg = compose_config([f"policy={policy}"], command="eval")
        assert cfg.train.lr == 1e-6 and list(cfg.train.betas) == [0.0, 0.999], policy
    loss_fn = OneDPSLoss(_actor(OneStepEDMSampler()), teacher=_actor(EDMHeunSampler(4)))
    trainer = Trainer(loss_fn.actor_network, loss_fn, total_steps=4, lr=1e-6, warmup_steps=0)
    generator, score = trainer.optimizer.param_groups
    assert generator["initial_lr"] == 1e-6 and score["initial_lr"] == pytest.approx(2e-5)
    assert {id(p) for p in score["params"]} == {id(p) for p in loss_fn.extra_parameters()}
    # a loss whose extra parameters share the actor's rate keeps one group (CP's stop-level offset)
    cp = ConsistencyLoss(
        _actor(ConsistencySampler(trajectory=True)), teacher=_actor(EDMHeunSampler(4)), trajectory=True
    )
    assert len(Trainer(cp.actor_network, cp, total_steps=2).optimizer.param_groups) == 1


@pytest.mark.parametrize("freeze", [True, False])
def test_consistency_keeps_the_students_encoder_at_the_teachers_as_cp_does(freeze):
    from l1flow_rl.modules.observations import STATE_KEY
    from l1flow_rl.networks.encoders.state import StateEncoder

    def actor(sampler):
        return L1FlowActor.build(
            StateEncoder({STATE_KEY: 5}, hidden_dims=(8,)),
            action_dim=2,
            down_dims=(16, 32),
            timestep_embed_dim=16,
            sampler=sampler,
            timestep_scale=EDM_SCALE,
        )

    torch.manual_seed(0)
    teacher, student = actor(EDMHeunSampler(4)), actor(ConsistencySampler())
    loss_fn = ConsistencyLoss(student, teacher=teacher, freeze_encoder=freeze)
    trainer = Trainer(student, loss_fn, total_steps=3, lr=1e-2, warmup_steps=0)
    encoder = {k: v.clone() for k, v in student.policy.encoder.state_dict().items()}
    for step in range(3):
        trainer.train_step(_batch(seed=step))
    after = student.policy.encoder.state_dict()
    assert all(torch.equal(after[k], v) for k, v in encoder.items()) == freeze
    assert any(
        not torch.equal(a, b) for a, b in zip(_net_state(student).values(), _net_state(teacher).values())
    )


@pytest.mark.parametrize(
    ("loss_cls", "teacher_sampler", "student_sampler", "message"),
    [
        (ConsistencyLoss, DDPMSampler(), ConsistencySampler(), r"\['karras'\]-prediction teacher"),
        (OneDPDLoss, DDPMSampler(), OneStepEDMSampler(stochastic=False), "use onedp_ddpm"),
        (OneDPSLoss, EDMHeunSampler(4), OneStepEDMSampler(stochastic=False), "stochastic=True"),
        (
            OneDPDLoss,
            DDPMSampler(),
            OneStepDDPMSampler(num_train_timesteps=50, t_init=30, stochastic=False),
            "trained with 100 steps",
        ),
    ],
)
def test_a_teacher_or_sampler_that_does_not_fit_is_refused_in_one_line(
    loss_cls, teacher_sampler, student_sampler, message
):
    with pytest.raises(ValueError, match=message) as err:
        loss_cls(_actor(student_sampler), teacher=_actor(teacher_sampler))
    assert "\n" not in str(err.value)


def test_the_trajectory_objective_conditions_on_the_stop_level_and_deploys_without_it():
    torch.manual_seed(0)
    teacher, student = _actor(EDMHeunSampler(4)), _actor(ConsistencySampler(trajectory=True))
    with pytest.raises(ValueError, match=r"give both the same") as err:
        ConsistencyLoss(student, teacher=teacher)  # a trajectory sampler for the plain objective
    assert "\n" not in str(err.value)
    loss_fn = ConsistencyLoss(student, teacher=teacher, trajectory=True)
    stop = loss_fn.stop_level
    assert torch.equal(stop(torch.tensor([0.02, 5.0, 80.0])), torch.zeros(3, stop.mlp[-1].out_features))
    trainer = Trainer(student, loss_fn, total_steps=3, lr=1e-2, warmup_steps=0)
    for step in range(3):
        trainer.train_step(_batch(seed=step))
    offsets = stop(torch.tensor([0.02, 5.0, 80.0])).abs().sum(-1)
    assert offsets[0] == 0 and (offsets[1:] > 0).all()  # learnt, and still nothing at sigma_min
    assert {k for k in trainer.state_dict()["loss_state"] if k.startswith("stop_level.")}


def test_a_trajectory_sampler_jumps_to_sigma_min_by_ctms_ratio():
    plain, ctm = ConsistencySampler(), ConsistencySampler(trajectory=True, clip_denoised=False)
    assert plain.training_signature() != ctm.training_signature()
    x = torch.randn(2, 16, 2)
    sigma = torch.tensor([3.0, 3.0])
    f = ctm.preconditioning.denoise(lambda xin, c: torch.zeros_like(xin), x, sigma)
    got = ctm._denoiser(lambda xin, c: torch.zeros_like(xin))(x, sigma)
    assert torch.allclose(got, (0.02 / 3.0) * x + (1 - 0.02 / 3.0) * f)


def test_a_distilled_teachers_ledger_keeps_its_own_teacher_and_old_checkpoints_count_their_steps():
    from l1flow_rl.workspace.teacher import teacher_ledger

    grand = {"stage": "teacher", "policy": "edm", "steps": 300, "batch_size": 64, "checkpoint": "edm.pt"}
    state = {"ledger": [grand, {"stage": "own", "policy": "consistency", "steps": 50, "batch_size": 64}]}
    assert teacher_ledger(state, "cp.pt") == [
        grand,
        {"stage": "teacher", "policy": "consistency", "steps": 50, "batch_size": 64, "checkpoint": "cp.pt"},
    ]
    old = {"config": {"policy": {"name": "ddpm"}, "train": {"batch_size": 32}}, "step": 1000}
    assert teacher_ledger(old, "ddpm.pt") == [
        {"stage": "teacher", "policy": "ddpm", "steps": 1000, "batch_size": 32, "checkpoint": "ddpm.pt"}
    ]


# -- teacher= at config time --------------------------------------------------------------------------


def _fake_checkpoint(path: Path, overrides: list[str]) -> Path:
    """A checkpoint whose recorded config is the run of ``overrides`` (only its config is read)."""
    cfg = OmegaConf.to_container(compose_config(overrides), resolve=True)
    return save_checkpoint(path, {"model": {}, "config": cfg, "step": 7})


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    d = tmp_path_factory.mktemp("teachers")
    return {
        "edm": _fake_checkpoint(d / "edm.pt", ["policy=edm"]),
        "other_task": _fake_checkpoint(d / "task.pt", ["policy=edm", "task=maniskill_pickcube"]),
        "other_net": _fake_checkpoint(d / "net.pt", ["policy=edm", "network.down_dims=[32,64,128]"]),
        "l1flow": _fake_checkpoint(d / "l1flow.pt", ["policy=l1flow", "network.timestep_scale=1000"]),
        "ddpm": _fake_checkpoint(d / "ddpm.pt", ["policy=ddpm", "network.timestep_scale=1000"]),
    }


@pytest.mark.parametrize(
    ("args", "teacher", "message"),
    [
        (
            ["policy=consistency"],
            None,
            r"teacher: policy\.loss='consistency' distils a teacher; pass teacher=",
        ),
        (["policy=onedp_s"], None, r"policy=edm or policy=ddpm run"),
        (["policy=l1flow"], "edm", r"trains from demonstrations alone; drop teacher="),
        (["policy=consistency"], "missing", r"teacher=.*does not exist"),
        (["policy=consistency"], "other_task", r"was trained on another task: task\.env_id 'PickCube-v1'"),
        (["policy=onedp_d"], "other_net", r"has another network: network\.down_dims \[32, 64, 128\]"),
        (
            ["policy=consistency"],
            "l1flow",
            r"policy='l1flow' checkpoint \('sample' prediction\), which cannot",
        ),
        (["policy=consistency"], "ddpm", r"cannot teach policy\.loss='consistency'; it distils policy=edm"),
        (["policy=onedp_d"], "ddpm", r"'epsilon'-prediction network, .* use policy\.sampler='onedp_ddpm'"),
        (["policy=onedp_s", "policy.sampler_kwargs.stochastic=false"], "edm", r"stochastic=True"),
        (["policy=consistency", "policy.loss_kwargs.trajectory=false"], "edm", r"give both the same"),
    ],
)
def test_teacher_problems_are_one_line_each_at_config_time(checkpoints, tmp_path, args, teacher, message):
    path = {None: None, "missing": tmp_path / "nope.pt"}.get(teacher, checkpoints.get(teacher))
    overrides = [*args, *([f"teacher={path}"] if path else [])]
    with pytest.raises(ConfigValidationError) as err:
        compose_config(overrides)
    header, *lines = str(err.value).splitlines()
    assert header == "1 config value(s) cannot work:", str(err.value)
    assert len(lines) == 1
    assert re.search(message, lines[0]), lines[0]


def test_a_fitting_teacher_passes_and_other_commands_ignore_it(checkpoints):
    for policy in ("consistency", "onedp_d", "onedp_s"):
        compose_config([f"policy={policy}", f"teacher={checkpoints['edm']}"])
    compose_config(
        [
            "policy=onedp_d",
            "policy.sampler=onedp_ddpm",
            "policy.sampler_kwargs={stochastic: false}",
            f"teacher={checkpoints['ddpm']}",
        ]
    )
    compose_config(["policy=l1flow", f"teacher={checkpoints['edm']}"], command="eval")


def test_the_cli_refuses_a_missing_teacher_before_any_work(tmp_path, capsys):
    run_dir = tmp_path / "run"
    assert main(["train", "policy=consistency", f"run_dir={run_dir}", f"data_dir={tmp_path}"]) == 2
    err = capsys.readouterr().err
    assert "teacher: policy.loss='consistency' distils a teacher" in err
    assert not run_dir.exists()


# -- end to end on the point-mass double --------------------------------------------------------------

E2E = [
    *TASK_OVERRIDES,
    "demos.num=4",
    "train.steps=20",
    "train.batch_size=16",
    "train.warmup_steps=2",
    "eval.episodes=1",
    "eval.num_envs=1",
    "network.down_dims=[16,32]",
    "network.timestep_embed_dim=16",
    "device=cpu",
]


@pytest.fixture(scope="module")
def edm_teacher(tmp_path_factory):
    root = tmp_path_factory.mktemp("distill")
    data, run = root / "data", root / "edm"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["train", *E2E, "policy=edm", f"data_dir={data}", f"run_dir={run}"]) == 0
    (root / "edm_stdout.txt").write_text(printed.getvalue())
    return root, run / "checkpoints" / "best.pt"


def _summary_rows(printed: str) -> set[str]:
    """The first words of the lines of the last printed summary table (between its dashed rules)."""
    lines = printed.splitlines()
    rules = [i for i, line in enumerate(lines) if line and set(line) == {"-"}]
    return {line.split()[0] for line in lines[rules[-2] + 1 : rules[-1]] if line.strip()}


def test_edm_trains_evaluates_and_rescores_at_another_step_count(edm_teacher):
    root, teacher = edm_teacher
    result = json.loads((teacher.parents[1] / "eval.json").read_text())
    assert result["sampler"]["name"] == "edm_heun" and result["sampler"]["nfe"] == 35
    assert result["ledger"] == [{"stage": "own", "policy": "edm", "steps": 20, "batch_size": 16}]
    assert result["total_steps_with_teacher"] == 20
    summary = json.loads((teacher.parents[1] / "summary.json").read_text())
    assert summary["total_steps_with_teacher"] == 20  # in the files, but a plain run does not print it
    rows = _summary_rows((root / "edm_stdout.txt").read_text())
    assert "success_once" in rows and not rows & {"ledger", "total_steps_with_teacher"}
    out = root / "edm_eval19"
    args = [*TASK_OVERRIDES, f"checkpoint={teacher}", "eval.episodes=1", f"run_dir={out}"]
    assert main(["eval", *args, "policy.sampler_kwargs.steps=10"]) == 0
    rescored = json.loads((out / "eval.json").read_text())
    assert rescored["sampler"]["nfe"] == 19 and rescored["sampler"]["trained_with"]["nfe"] == 35


@pytest.mark.parametrize("policy", ["consistency", "onedp_d", "onedp_s"])
def test_a_student_trains_from_the_teacher_checkpoint_and_its_ledger_counts_both(edm_teacher, policy, capsys):
    root, teacher = edm_teacher
    run = root / policy
    args = [*E2E, f"policy={policy}", f"teacher={teacher}", f"data_dir={root / 'data'}", f"run_dir={run}"]
    assert main(["train", *args]) == 0
    assert {"ledger", "total_steps_with_teacher"} <= _summary_rows(capsys.readouterr().out)
    want = [
        {"stage": "teacher", "policy": "edm", "steps": 20, "batch_size": 16, "checkpoint": str(teacher)},
        {"stage": "own", "policy": policy, "steps": 20, "batch_size": 16},
    ]
    result = json.loads((run / "eval.json").read_text())
    assert result["episodes"] == 1 and result["sampler"]["nfe"] == 1
    assert result["ledger"] == want and result["total_steps_with_teacher"] == 40
    assert json.loads((run / "history.json").read_text())["ledger"] == want
    assert json.loads((run / "summary.json").read_text())["total_steps_with_teacher"] == 40
    latest = load_checkpoint(run / "checkpoints" / "latest.pt")
    assert latest["ledger"] == want and latest["config"]["teacher"] == str(teacher)
    if policy != "onedp_d":  # the target network / the score network travel in the checkpoint
        assert latest["loss_state"]
    if policy == "consistency":  # and CP re-scores at 3 steps through the sampler swap
        out = root / "cp3"
        eval_args = [*TASK_OVERRIDES, f"checkpoint={run / 'checkpoints' / 'best.pt'}", "eval.episodes=1"]
        assert main(["eval", *eval_args, "policy.sampler_kwargs.steps=3", f"run_dir={out}"]) == 0
        rescored = json.loads((out / "eval.json").read_text())
        assert rescored["sampler"]["nfe"] == 3 and rescored["ledger"] == want
