"""``l1flow-rl finetune`` end to end on the real ManiSkill PushCube: a BC checkpoint in, the start
validated, offline then online updates (TorchRL collector, 2 worker envs), eval.json and checkpoints
out, and exact resume of an online run killed mid-way."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

pytest.importorskip("mani_skill", reason="needs ManiSkill: pip install 'l1flow-rl[maniskill]'")

from l1flow_rl import BestOfNActor, NoiseActor
from l1flow_rl.commands.cli import main
from l1flow_rl.finetune.base import Learner
from l1flow_rl.finetune.proposal_cache import ProposalCache
from l1flow_rl.workspace.checkpoint import (
    CheckpointMismatchError,
    ResumeMismatchError,
    load_actor,
    load_checkpoint,
)

pytestmark = pytest.mark.maniskill

BC = [
    "demos.num=3",
    "train.steps=20",
    "eval.episodes=1",
    "eval.num_envs=1",
    "network.down_dims=[16,32]",
    "network.timestep_embed_dim=16",
    "task.max_episode_steps=30",
]

# 4 offline updates, then 2 rounds of 40 env steps (2 envs x 20): the first is the warm-up (the BC
# start acts, no update), the second is followed by 0.1 x 40 = 4 updates; a checkpoint after each round.
FT = [
    "offline.steps=4",
    "online.steps=80",
    "online.warmup_steps=40",
    "online.num_envs=2",
    "online.frames_per_round=40",
    "online.updates_per_step=0.1",
    "online.checkpoint_every=40",
    "finetune.batch_size=16",
    "finetune.critic_hidden_dims=[32,32]",
    "finetune.qc.num_samples=4",
    "finetune.log_every=2",
    "eval.episodes=2",
    "eval.num_envs=1",
    "task.max_episode_steps=20",
]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("demos")


@pytest.fixture(scope="module")
def bc_checkpoint(tmp_path_factory, data_dir):
    run_dir = tmp_path_factory.mktemp("bc") / "run"
    assert main(["train", f"data_dir={data_dir}", f"run_dir={run_dir}", *BC]) == 0
    return run_dir / "checkpoints" / "latest.pt"


def _args(run_dir, data_dir, bc_checkpoint, *extra):
    return [
        "finetune",
        f"checkpoint={bc_checkpoint}",
        f"data_dir={data_dir}",
        f"run_dir={run_dir}",
        *FT,
        *extra,
    ]


@pytest.fixture(scope="module")
def finetuned(tmp_path_factory, data_dir, bc_checkpoint):
    run_dir = tmp_path_factory.mktemp("ft") / "run"
    assert main(_args(run_dir, data_dir, bc_checkpoint, "finetune=qc")) == 0
    return run_dir


def _differing(a: dict, b: dict) -> list[str]:
    return [k for k in a if isinstance(a[k], torch.Tensor) and not torch.equal(a[k], b[k])]


def test_qc_validates_the_start_then_fine_tunes_offline_and_online(finetuned):
    result = json.loads((finetuned / "eval.json").read_text())
    assert result["episodes"] == 2 and result["split"] == "test" and 0.0 <= result["success_once"] <= 1.0
    state = load_checkpoint(finetuned / "checkpoints" / "latest.pt")
    assert state["progress"] == {
        "offline_updates": 4,
        "online_updates": 4,
        "env_steps": 80,
        "rounds": 2,
        "started": True,
    }
    assert (finetuned / "checkpoints" / state["online_buffer"]).is_dir()
    history = json.loads((finetuned / "history.json").read_text())
    evals = history["evals"]
    assert evals[0]["phase"] == "start" and evals[0]["step"] == 0  # the BC start competes
    # ... and a later model must beat it by more than its standard error (the "start" rule)
    assert evals[0]["standard_error"] >= 0
    assert "the start (the first) kept unless" in result["selection"]["rule"]
    rounds = history["rounds"]
    assert [r["env_steps"] for r in rounds] == [40, 80] and [r["policy"] for r in rounds] == [
        "start",
        "actor",
    ]
    assert [r["updates"] for r in rounds] == [0, 4] and rounds[1]["updates_per_s"] > 0
    assert all(r["env_steps_per_s"] > 0 and r["steps_stored"] == 40 for r in rounds)
    summary = json.loads((finetuned / "summary.json").read_text())
    assert summary["algorithm"] == "qc" and summary["online_updates"] == 4


def test_the_run_records_and_trains_on_the_data_its_start_was_trained_on(finetuned):
    from omegaconf import OmegaConf

    # BC made 3 demonstrations; the fine-tune command names none: its record says 3 (not the default 100)
    assert OmegaConf.load(finetuned / "config.yaml").demos.num == 3
    history = json.loads((finetuned / "history.json").read_text())
    assert history["demo_episodes"][0]["given"] == 3


def test_the_critic_bias_bench_reloads_a_finished_run_with_its_data(finetuned):
    from benchmarks.finetune.bench_critic_bias import load_run

    # it reads the run's data through the fine-tune job's own rule, and
    # broke when that rule's signature changed
    cfg, actor, episodes = load_run(finetuned)
    assert cfg.finetune.algorithm == "qc" and cfg.demos.num == 3
    assert int(episodes["episode"].unique().numel()) == 3
    assert actor.in_keys and actor.out_keys


def test_the_checkpoint_rebuilds_the_best_of_n_actor_for_eval(tmp_path, finetuned):
    actor, cfg = load_actor(finetuned / "checkpoints" / "latest.pt")
    assert (
        isinstance(actor, BestOfNActor) and actor.num_samples == 4 and cfg.policy.finetune.algorithm == "qc"
    )
    out = tmp_path / "eval"
    ckpt = finetuned / "checkpoints" / "latest.pt"
    args = ["eval", f"checkpoint={ckpt}", "eval.episodes=1", "eval.num_envs=1", "task.max_episode_steps=20"]
    assert main([*args, f"run_dir={out}"]) == 0


def _killed_and_resumed(run_dir, args, monkeypatch, kill_at: int = 4 + 2, saved: dict | None = None) -> dict:
    """``args`` killed at update ``kill_at`` (default: the second of the online updates), then resumed
    from the last checkpoint (default: after the first round; ``saved``: the progress it holds): the
    resumed run's last checkpoint."""
    saved = saved or {"env_steps": 40}
    real_update, calls = Learner.update, {"n": 0}

    def crashing_update(self, batch, **kwargs):
        calls["n"] += 1
        if calls["n"] == kill_at:
            raise RuntimeError("simulated kill")
        return real_update(self, batch, **kwargs)

    monkeypatch.setattr(Learner, "update", crashing_update)
    with pytest.raises(RuntimeError, match="simulated kill"):
        main(args)
    progress = load_checkpoint(run_dir / "checkpoints" / "latest.pt")["progress"]
    assert {k: progress[k] for k in saved} == saved
    monkeypatch.setattr(Learner, "update", real_update)
    assert main([*args, "resume=true"]) == 0
    return load_checkpoint(run_dir / "checkpoints" / "latest.pt")


def _assert_same_run(resumed: dict, straight: dict) -> None:
    assert resumed["progress"] == straight["progress"]
    assert _differing(resumed["model"], straight["model"]) == []
    if straight.get("ema") is not None:  # finetune.ema_power: the averaged actor and its step counter
        assert _differing(resumed["ema"], straight["ema"]) == []
        assert torch.equal(resumed["ema_n_averaged"], straight["ema_n_averaged"])
    assert _differing(resumed["loss"], straight["loss"]) == []
    assert _differing(resumed["buffers"], straight["buffers"]) == []
    # logged metrics (NaN where a round had no update: the warm-up) equal, NaN included
    np.testing.assert_array_equal(resumed["history"]["loss_qvalue"], straight["history"]["loss_qvalue"])
    strip = lambda rows: [{k: v for k, v in r.items() if not k.endswith("_per_s")} for r in rows]  # noqa: E731
    assert strip(resumed["records"]["rounds"]) == strip(straight["records"]["rounds"])


def test_resume_of_an_online_run_killed_mid_way_matches_an_uninterrupted_run(
    tmp_path, data_dir, bc_checkpoint, finetuned, monkeypatch
):
    """The same weights, critics, optimiser, buffers, logged rounds as the uninterrupted run (evaluation
    off here, which also shows that evaluating leaves training untouched)."""
    run_dir = tmp_path / "run"
    args = _args(run_dir, data_dir, bc_checkpoint, "finetune=qc", "eval.enabled=false")
    resumed = _killed_and_resumed(run_dir, args, monkeypatch)
    _assert_same_run(resumed, load_checkpoint(finetuned / "checkpoints" / "latest.pt"))


def test_an_offline_phase_killed_mid_way_resumes_from_its_last_checkpoint_as_the_uninterrupted_run(
    tmp_path, data_dir, bc_checkpoint, finetuned, monkeypatch
):
    """offline.checkpoint_every=2: killed at the third of the 4 offline updates, the run resumes from
    the 2 saved (not from the start) and ends where the uninterrupted run ends, online phase included."""
    run_dir = tmp_path / "run"
    args = _args(
        run_dir, data_dir, bc_checkpoint, "finetune=qc", "eval.enabled=false", "offline.checkpoint_every=2"
    )
    resumed = _killed_and_resumed(
        run_dir, args, monkeypatch, kill_at=3, saved={"offline_updates": 2, "env_steps": 0}
    )
    _assert_same_run(resumed, load_checkpoint(finetuned / "checkpoints" / "latest.pt"))


@pytest.mark.slow  # ~30 s; exact resume is test_resume_of_an_online_run_killed_mid_way's by default
def test_a_finished_run_resumed_with_more_env_steps_goes_on_as_the_longer_run(
    tmp_path, data_dir, bc_checkpoint, finetuned
):
    """online.steps=40 run to its end, then resumed with online.steps=80: the same weights, critics,
    optimiser, buffers and rounds as the 80-step run (its online buffer, dumped at 40 + one round's
    rows, grows to 80 + one round's); the first report is kept; a resume cannot shorten a run or
    grow its offline phase once it went online."""
    run_dir = tmp_path / "run"
    args = _args(run_dir, data_dir, bc_checkpoint, "finetune=qc")
    short = [a if a != "online.steps=80" else "online.steps=40" for a in args]
    assert main(short) == 0
    first = json.loads((run_dir / "eval.json").read_text())
    assert load_checkpoint(run_dir / "checkpoints" / "latest.pt")["progress"]["env_steps"] == 40
    for bad, says in (
        ("online.steps=20", r"online\.steps=20: the run has already taken 40 env steps"),
        ("offline.steps=6", r"offline\.steps=6: the run made 4 offline updates and went online"),
    ):
        with pytest.raises(ResumeMismatchError, match=says):
            main(["--debug", *args, bad, "resume=true"])
    assert main([*args, "resume=true"]) == 0
    _assert_same_run(
        load_checkpoint(run_dir / "checkpoints" / "latest.pt"),
        load_checkpoint(finetuned / "checkpoints" / "latest.pt"),
    )
    assert json.loads((run_dir / "eval_step44.json").read_text()) == first  # 4 updates + 40 env steps
    assert json.loads((run_dir / "summary_step44.json").read_text())["env_steps"] == 40
    assert json.loads((run_dir / "summary.json").read_text())["env_steps"] == 80


def test_frozen_qc_resumes_exactly_with_its_proposal_cache_redrawn(
    tmp_path, data_dir, bc_checkpoint, monkeypatch
):
    """The cache is not checkpointed: a resumed run redraws each observation's proposals from the same
    per-observation noise, so its critics match the uninterrupted run's bit for bit."""
    frozen = ("finetune=qc", "finetune.qc.freeze_flow=true", "eval.enabled=false")
    straight_dir = tmp_path / "straight"
    served, real_call = [], ProposalCache.__call__
    monkeypatch.setattr(ProposalCache, "__call__", lambda self, obs: served.append(1) or real_call(self, obs))
    assert main(_args(straight_dir, data_dir, bc_checkpoint, *frozen)) == 0
    assert len(served) == 4 + 4  # every offline and online update's backup went through the cache
    monkeypatch.setattr(ProposalCache, "__call__", real_call)
    straight = load_checkpoint(straight_dir / "checkpoints" / "latest.pt")
    run_dir = tmp_path / "run"
    resumed = _killed_and_resumed(run_dir, _args(run_dir, data_dir, bc_checkpoint, *frozen), monkeypatch)
    _assert_same_run(resumed, straight)
    flow = load_actor(bc_checkpoint)[0].state_dict()
    tuned = {k.removeprefix("actor."): v for k, v in resumed["model"].items() if k.startswith("actor.")}
    assert tuned.keys() == flow.keys() and _differing(tuned, flow) == []  # the flow stayed as it was


def test_a_checkpoint_of_another_task_is_refused(tmp_path, data_dir, bc_checkpoint):
    with pytest.raises(CheckpointMismatchError, match=r"task\.env_id"):
        main(
            [
                "--debug",  # raised, not printed as one line
                "finetune",
                f"checkpoint={bc_checkpoint}",
                f"data_dir={data_dir}",
                f"run_dir={tmp_path / 'x'}",
                "task=maniskill_pickcube",
            ]
        )


def test_steering_online_stores_the_chunk_input_and_leaves_the_flow_as_it_was(
    tmp_path, data_dir, bc_checkpoint, monkeypatch
):
    from l1flow_rl.workspace.harness import Run

    validated = []
    original = Run.validate

    def spy(self, actor, step, **row):  # records which module each validation acted with
        validated.append((row.get("phase"), type(actor).__name__))
        return original(self, actor, step, **row)

    monkeypatch.setattr(Run, "validate", spy)
    run_dir = tmp_path / "dsrl"
    overrides = [
        "finetune=dsrl",
        "offline.steps=0",
        "finetune.dsrl.actor_hidden_dims=[32]",
        "eval.enabled=false",
    ]
    assert main(_args(run_dir, data_dir, bc_checkpoint, *overrides)) == 0
    # the start that competes for best.pt is the BC checkpoint itself, not the warm-up actor
    assert validated[0] == ("start", "L1FlowActor")
    state = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert state["progress"]["online_updates"] == 4 and state["progress"]["offline_updates"] == 0
    actor, _ = load_actor(run_dir / "checkpoints" / "latest.pt")
    assert isinstance(actor, NoiseActor)
    policy = actor.policy
    assert actor.noise_policy.noise_shape == (policy.pred_horizon, policy.action_dim)
    bc = load_checkpoint(bc_checkpoint)
    flow = {k[len("flow.") :]: v for k, v in state["model"].items() if k.startswith("flow.")}
    assert flow and all(torch.equal(v, bc["ema"][k]) for k, v in flow.items())  # frozen
    # batches hold chunk starts only (every-step windows left 1 in action_steps valid); only a chunk
    # that crosses a truncated end drops out
    logged = (run_dir / "logs" / "finetune" / "scalars" / "online" / "valid_fraction.csv").read_text()
    fractions = [float(line.split(",")[1]) for line in logged.split()]
    assert fractions and min(fractions) > 0.5, fractions


def test_dsrl_na_learns_from_demonstrations_with_the_flow_frozen_and_resumes_exactly(
    tmp_path, data_dir, bc_checkpoint, monkeypatch
):
    """DSRL-NA's action critic trains on the demonstrations (offline updates, then half of each online
    batch), the steering actor acts, the flow stays the BC checkpoint's, and a run killed mid-way
    resumes to the uninterrupted run's weights (the distillation's cached noises are redrawn alike)."""
    na = ("finetune=dsrl_na", "finetune.dsrl_na.actor_hidden_dims=[32]", "finetune.dsrl_na.distill_samples=2")
    straight_dir = tmp_path / "straight"
    assert main(_args(straight_dir, data_dir, bc_checkpoint, *na, "eval.enabled=false")) == 0
    straight = load_checkpoint(straight_dir / "checkpoints" / "latest.pt")
    assert straight["progress"]["offline_updates"] == 4 and straight["progress"]["online_updates"] == 4
    actor, _ = load_actor(straight_dir / "checkpoints" / "latest.pt")
    assert isinstance(actor, NoiseActor)
    bc = load_checkpoint(bc_checkpoint)
    flow = {k[len("flow.") :]: v for k, v in straight["model"].items() if k.startswith("flow.")}
    assert flow and all(torch.equal(v, bc["ema"][k]) for k, v in flow.items())  # frozen
    # every window is valued by its executed actions (no chunk-start filter as plain DSRL's)
    logged = (straight_dir / "logs" / "finetune" / "scalars" / "online" / "valid_fraction.csv").read_text()
    assert min(float(line.split(",")[1]) for line in logged.split()) > 0.5
    run_dir = tmp_path / "run"
    resumed = _killed_and_resumed(
        run_dir, _args(run_dir, data_dir, bc_checkpoint, *na, "eval.enabled=false"), monkeypatch
    )
    _assert_same_run(resumed, straight)


def test_filtered_bc_trains_the_flow_on_demonstrations_and_successful_episodes_only(
    tmp_path, data_dir, bc_checkpoint
):
    from l1flow_rl import L1FlowActor

    run_dir = tmp_path / "filtered_bc"
    overrides = ["finetune=filtered_bc", "finetune.batch_size=16", "eval.enabled=false"]
    assert main(_args(run_dir, data_dir, bc_checkpoint, *overrides)) == 0
    state = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert state["progress"]["online_updates"] == 4 and state["progress"]["offline_updates"] == 4
    actor, _ = load_actor(run_dir / "checkpoints" / "latest.pt")
    assert isinstance(actor, L1FlowActor)  # the flow itself acts and is trained
    bc = load_checkpoint(bc_checkpoint)
    assert any(not torch.equal(v, bc["ema"][k]) for k, v in state["model"].items())
    # every online round reports how many windows the successful episodes give, and batches drawn
    # from the demonstrations alone while none had succeeded
    rounds = json.loads((run_dir / "summary.json").read_text())
    logged = run_dir / "logs" / "finetune" / "scalars" / "online"
    windows = [float(line.split(",")[1]) for line in (logged / "online_windows.csv").read_text().split()]
    succeeded = [
        float(line.split(",")[1]) for line in (logged / "episodes_succeeded.csv").read_text().split()
    ]
    assert len(windows) == 2 and (windows[-1] > 0) == (sum(succeeded) > 0), (windows, succeeded, rounds)


@pytest.mark.parametrize("preset", ["filtered_bc", "qc"])
def test_with_an_ema_the_averaged_flow_is_saved_for_eval_and_resumes_exactly(
    tmp_path, data_dir, bc_checkpoint, monkeypatch, preset
):
    """finetune.ema_power: the raw flow trains, its EMA (one step per update) is what load_actor, hence
    eval, validation and the test, get; a run killed mid-way resumes to the same EMA. QC acts with the
    averaged flow proposing and its online critics picking."""
    args = [f"finetune={preset}", "finetune.batch_size=16", "finetune.ema_power=0.75", "eval.enabled=false"]
    straight_dir = tmp_path / "straight"
    assert main(_args(straight_dir, data_dir, bc_checkpoint, *args)) == 0
    straight = load_checkpoint(straight_dir / "checkpoints" / "latest.pt")
    updates = straight["progress"]["offline_updates"] + straight["progress"]["online_updates"]
    # the flow's EMA goes on from the BC run's (its counter), not from a copy of the first iterate
    bc_count = int(load_checkpoint(bc_checkpoint)["ema_n_averaged"])
    assert updates == 8 and bc_count > 0 and int(straight["ema_n_averaged"]) == bc_count + updates
    assert _differing(straight["ema"], straight["model"]) != []  # averaged, not the last iterate
    actor, _ = load_actor(straight_dir / "checkpoints" / "latest.pt")
    assert _differing(actor.state_dict(), straight["ema"]) == []
    if preset == "qc":  # the flow averaged, the critics that pick are the online ones, not averaged
        assert isinstance(actor, BestOfNActor)
        averaged = _differing(straight["ema"], straight["model"])
        assert averaged and all(k.startswith("actor.") for k in averaged), averaged
        critic = {k: v for k, v in straight["model"].items() if k.startswith("critic.")}
        assert critic and _differing(critic, {k: straight["ema"][k] for k in critic}) == []
    run_dir = tmp_path / "resumed"
    resumed = _killed_and_resumed(run_dir, _args(run_dir, data_dir, bc_checkpoint, *args), monkeypatch)
    _assert_same_run(resumed, straight)
    # a resume cannot switch the EMA off or on: the weights that act would change meaning
    with pytest.raises(CheckpointMismatchError, match=r"finetune\.ema_power: checkpoint has 0.75"):
        without = _args(
            run_dir, data_dir, bc_checkpoint, *args[:2], "finetune.ema_power=0", "eval.enabled=false"
        )
        main(["--debug", *without, "resume=true"])


def test_the_continued_bc_control_trains_on_demonstrations_without_an_env_step(
    tmp_path, data_dir, bc_checkpoint
):
    """bench_finetune_online's continued-BC control: filtered BC's offline phase alone, validated."""
    from benchmarks.finetune.bench_finetune_online import continued_bc_cmd

    run_dir = tmp_path / "continued_bc"
    args = type(
        "Args", (), {"continued_bc_updates": 4, "checkpoint": bc_checkpoint, "task": "maniskill_pushcube"}
    )
    args.test_episodes, args.val_episodes, args.override = 2, 1, [f"data_dir={data_dir}", *FT[-2:]]
    cmd = continued_bc_cmd(0, args, run_dir)
    assert cmd[3:5] == ["finetune", "finetune=filtered_bc"] and "online.steps=0" in cmd
    assert main([*cmd[3:], "finetune.batch_size=16"]) == 0
    state = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert state["progress"]["offline_updates"] == 4 and state["progress"]["env_steps"] == 0
    history = json.loads((run_dir / "history.json").read_text())
    phases = [(e.get("phase"), e.get("updates")) for e in history["evals"] if e.get("split") == "val"]
    assert phases[:2] == [("start", 0), ("offline", 1)] and ("offline", 4) in phases, phases
    bc = load_checkpoint(bc_checkpoint)
    assert any(not torch.equal(v, bc["ema"][k]) for k, v in state["model"].items())
    assert json.loads((run_dir / "eval.json").read_text())["episodes"] == 2
    # the bench extends a finished control (--continued-bc-updates 6): the 6-update run's weights
    args.continued_bc_updates = 6
    assert main([*continued_bc_cmd(0, args, run_dir)[3:], "finetune.batch_size=16", "resume=true"]) == 0
    straight_dir = tmp_path / "straight"
    assert main([*continued_bc_cmd(0, args, straight_dir)[3:], "finetune.batch_size=16"]) == 0
    extended, straight = (load_checkpoint(d / "checkpoints" / "latest.pt") for d in (run_dir, straight_dir))
    assert extended["progress"] == straight["progress"] and straight["progress"]["offline_updates"] == 6
    assert _differing(extended["model"], straight["model"]) == []
    assert _differing(extended["ema"], straight["ema"]) == []
    assert (run_dir / "eval_step4.json").is_file() and (run_dir / "eval.json").is_file()


def test_an_fql_run_trains_its_one_step_actor_and_its_checkpoint_evaluates(tmp_path, data_dir, bc_checkpoint):
    """FQL's acting module is its one-step actor mu (no sampler): ``l1flow-rl eval`` of its checkpoint
    names it by class with its counted NFE (it crashed writing eval.json after its episodes)."""
    from l1flow_rl import OneStepActor

    run_dir = tmp_path / "fql"
    overrides = ["finetune=fql", "finetune.fql.actor_hidden_dims=[32]", "eval.enabled=false"]
    assert main(_args(run_dir, data_dir, bc_checkpoint, *overrides)) == 0
    ckpt = run_dir / "checkpoints" / "latest.pt"
    assert load_checkpoint(ckpt)["progress"]["online_updates"] == 4
    actor, _ = load_actor(ckpt)
    assert isinstance(actor, OneStepActor)
    out = tmp_path / "eval"
    args = ["eval", f"checkpoint={ckpt}", "eval.episodes=1", "eval.num_envs=1", "task.max_episode_steps=20"]
    assert main([*args, f"run_dir={out}"]) == 0
    sampler = json.loads((out / "eval.json").read_text())["sampler"]
    assert sampler["name"] == "OneStepActor" and sampler["nfe"] == 1.0 and sampler["trained_with"] is None


def test_the_online_bench_tells_a_start_from_a_remade_one_by_its_weights(tmp_path, bc_checkpoint):
    """bench_finetune_online records its start's fingerprint: a start remade by its own command on
    another machine can differ, and its controls and seeds then compare against another start."""
    from benchmarks.finetune.bench_finetune_online import start_fingerprint
    from l1flow_rl.workspace.checkpoint import load_checkpoint, save_checkpoint

    first = start_fingerprint(bc_checkpoint)
    assert first == start_fingerprint(bc_checkpoint)
    assert len(first["weights_sha256"]) == 64 and len(first["episodes_sha256"]) == 64
    state = load_checkpoint(bc_checkpoint)
    name = sorted(state["model"])[0]
    state["model"][name] = state["model"][name] + 1.0  # one tensor differs; the episodes are the same
    remade = start_fingerprint(save_checkpoint(tmp_path / "remade.pt", state))
    assert remade["weights_sha256"] != first["weights_sha256"]
    assert remade["episodes_sha256"] == first["episodes_sha256"]
