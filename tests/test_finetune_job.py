"""``l1flow-rl finetune`` end to end on the real ManiSkill PushCube: a BC checkpoint in, offline then
online FlowQ updates (TorchRL collector, 2 worker envs), eval.json and checkpoints out, exact resume."""

from __future__ import annotations

import json
import math

import pytest
import torch
import yaml

pytest.importorskip("mani_skill", reason="needs ManiSkill: pip install 'l1flow-rl[maniskill]'")

from l1flow_rl.cli import main
from l1flow_rl.workspace.checkpoint import CheckpointMismatchError, load_actor, load_checkpoint
from l1flow_rl.workspace.flowq_trainer import FlowQTrainer

pytestmark = pytest.mark.maniskill

BC = [
    "demos.num=3",
    "train.steps=20",
    "eval.episodes=1",
    "eval.num_envs=1",
    "policy.down_dims=[16,32]",
    "policy.timestep_embed_dim=16",
    "task.max_episode_steps=30",
]

# 6 offline updates (checkpoints at 3 and 6), then 2 rounds of 40 env steps (2 envs x 20) with 4
# updates each (a checkpoint after each round), then 2 test episodes.
FT = [
    "offline.steps=6",
    "online.steps=80",
    "online.num_envs=2",
    "online.frames_per_round=40",
    "online.updates_per_step=0.1",
    "finetune.batch_size=16",
    "finetune.critic_hidden_dims=[32,32]",
    "finetune.log_every=2",
    "finetune.checkpoint_every=3",
    "eval.episodes=2",
    "eval.num_envs=1",
    "task.max_episode_steps=20",  # a round gives each env a whole episode: 2 envs x 20 steps
]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("demos")


@pytest.fixture(scope="module")
def bc_checkpoint(tmp_path_factory, data_dir):
    run_dir = tmp_path_factory.mktemp("bc") / "run"
    assert main(["train", f"data_dir={data_dir}", f"run_dir={run_dir}", *BC]) == 0
    return run_dir / "checkpoints" / "latest.pt"


@pytest.fixture(scope="module")
def finetuned(tmp_path_factory, data_dir, bc_checkpoint):
    run_dir = tmp_path_factory.mktemp("ft") / "run"
    args = ["finetune", f"checkpoint={bc_checkpoint}", f"data_dir={data_dir}", f"run_dir={run_dir}", *FT]
    assert main(args) == 0
    return run_dir


def _differing(a: dict, b: dict) -> list[str]:
    return [k for k in a if isinstance(a[k], torch.Tensor) and not torch.equal(a[k], b[k])]


def test_finetune_offline_then_online_writes_eval_and_checkpoints(finetuned, bc_checkpoint):
    result = json.loads((finetuned / "eval.json").read_text())
    assert result["episodes"] == 2 and result["split"] == "test"
    assert result["env_steps"] == 80 and result["updates"] == 6 + 8 and result["mode"] == "distill"
    assert 0.0 <= result["success_once"] <= 1.0
    state = load_checkpoint(finetuned / "checkpoints" / "latest.pt")
    assert state["progress"] == {"offline_updates": 6, "online_round": 2, "env_steps": 80}
    assert (finetuned / "checkpoints" / state["online_buffer"]).is_dir()
    assert (finetuned / "checkpoints" / "best.pt").is_file()
    history = json.loads((finetuned / "history.json").read_text())
    assert set(history["history"]["phase"]) == {"offline", "online"}
    for m in history["history"]["metrics"]:
        assert {
            "q_mean",
            "q_data_mean",
            "target_mean",
            "bc_loss",
            "distill_loss",
            "lambda",
            "bc_distance",
        } <= set(m)
    # two rounds of 2 envs x 20 steps: every step stored (episodes end at success or the time limit)
    assert [r["env_steps"] for r in history["rounds"]] == [40, 80]
    assert [r["steps_stored"] for r in history["rounds"]] == [40, 40]
    assert (finetuned / "finetune.png").stat().st_size > 1000
    scalars = {p.relative_to(finetuned / "logs").as_posix() for p in (finetuned / "logs").rglob("*.csv")}
    for name in (
        "offline/q_mean",
        "online/q_mean",
        "online/bc_distance",
        "collect/episodes_succeeded",
        "env_steps",
    ):
        assert f"finetune/scalars/{name}.csv" in scalars, name
    # the fine-tuned actor differs from the BC policy, and the BC run's checkpoint is untouched
    bc = load_checkpoint(bc_checkpoint)
    assert _differing(state["model"], bc["ema"])
    assert bc["step"] == 20


def test_the_finetuned_checkpoint_is_an_ordinary_actor_for_eval(tmp_path, finetuned):
    ckpt = finetuned / "checkpoints" / "latest.pt"
    actor, cfg = load_actor(ckpt)
    assert actor.sampler.nfe == 1 and cfg.policy.sampler == "euler"  # mu(s, z) = f(z, 0 | s)
    out = tmp_path / "eval"
    args = ["eval", f"checkpoint={ckpt}", "eval.episodes=2", "eval.num_envs=1", "task.max_episode_steps=30"]
    assert main([*args, f"run_dir={out}"]) == 0
    assert json.loads((out / "eval.json").read_text())["episodes"] == 2


def test_resume_matches_an_uninterrupted_run(tmp_path, data_dir, bc_checkpoint, finetuned, monkeypatch):
    """Crash in the second online round, resume from the checkpoint after the first: the same
    weights, critics, optimiser, logged metrics and collected rounds as the uninterrupted run. This
    run skips evaluation (eval.* may change on resume), which also shows evaluating leaves training
    untouched."""
    run_dir = tmp_path / "run"
    args = [
        "finetune",
        f"checkpoint={bc_checkpoint}",
        f"data_dir={data_dir}",
        f"run_dir={run_dir}",
        *FT,
        "eval.episodes=0",
    ]
    real_update = FlowQTrainer.update

    def crashing_update(self, batch, actor=True, critic="td"):
        if self.updates == 12:  # inside the second online round
            raise RuntimeError("simulated crash at update 12")
        return real_update(self, batch, actor=actor, critic=critic)

    monkeypatch.setattr(FlowQTrainer, "update", crashing_update)
    with pytest.raises(RuntimeError, match="simulated crash"):
        main(args)
    saved = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert saved["progress"] == {"offline_updates": 6, "online_round": 1, "env_steps": 40}
    monkeypatch.setattr(FlowQTrainer, "update", real_update)

    with pytest.raises(FileExistsError, match="resume=true"):
        main(args)
    with pytest.raises(CheckpointMismatchError, match=r"finetune\.alpha"):  # --debug: raised, not printed
        main(["--debug", *args, "resume=true", "finetune.alpha=5"])
    assert main([*args, "resume=true"]) == 0
    resumed = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    straight = load_checkpoint(finetuned / "checkpoints" / "latest.pt")
    assert resumed["progress"] == straight["progress"]
    assert _differing(resumed["model"], straight["model"]) == []
    assert _differing(resumed["trainer"]["loss"], straight["trainer"]["loss"]) == []
    assert _differing(resumed["buffers"], straight["buffers"]) == []  # the samplers' generators
    assert resumed["history"]["metrics"] == straight["history"]["metrics"]
    assert resumed["rounds"] == straight["rounds"]
    # The run's cost counts the crashed invocation too, up to its last checkpoint; the offline phase
    # ended before the crash, so the resumed invocation adds nothing to it.
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["seconds_since_step"] == 0
    assert summary["machine"]["device"] == "cpu" and summary["machine"]["torch_threads"] >= 1
    assert summary["offline_seconds"] == pytest.approx(saved["elapsed"]["offline"], abs=0.06)
    for phase in ("online", "cpu", "wall"):
        assert summary[f"{phase}_seconds"] > round(saved["elapsed"][phase], 1), phase


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


def test_direct_mode_offline_only_keeps_the_two_step_actor(tmp_path, data_dir, bc_checkpoint):
    run_dir = tmp_path / "direct"
    args = [
        "finetune",
        f"checkpoint={bc_checkpoint}",
        f"data_dir={data_dir}",
        f"run_dir={run_dir}",
        "finetune.mode=direct",
        "finetune.alpha=2.5",
        "finetune.batch_size=16",
        "finetune.critic_hidden_dims=[32]",
        "offline.steps=5",
        "offline.critic_pretrain=1",
        "offline.critic_warmup=2",
        "finetune.log_every=1",
        "online.steps=0",
        "eval.episodes=0",
    ]
    assert main(args) == 0
    state = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert state["progress"] == {"offline_updates": 5, "online_round": 0, "env_steps": 0}
    # the first update fits the Monte-Carlo returns, the next 2 train the critics alone by TD (no
    # actor loss), the last 2 both
    metrics = json.loads((run_dir / "history.json").read_text())["history"]["metrics"]
    assert ["loss_actor" in m for m in metrics] == [False, False, False, True, True]
    assert all("loss_qvalue" in m and "bc_distance" in m for m in metrics)
    assert all(math.isfinite(m["q_mc_corr"]) and m["q_chunk_std"] >= 0 for m in metrics)
    assert state["online_buffer"] is None
    actor, cfg = load_actor(run_dir / "checkpoints" / "latest.pt")
    assert actor.sampler.nfe == 2 and cfg.policy.sampler == "two_step"
    assert _differing(state["model"], load_checkpoint(bc_checkpoint)["ema"])
    assert not (run_dir / "eval.json").exists()


def test_best_of_n_offline_then_online_acts_with_its_critics_and_evaluates(tmp_path, data_dir, bc_checkpoint):
    """QC's best-of-N: the critics (reading residual chunks) train by Monte-Carlo, then TD with the
    mean backup over 2 draws; the BC network does not; the collector and the evaluation act with the
    selecting actor, and ``l1flow-rl eval`` reloads it as one."""
    run_dir = tmp_path / "qc"
    args = [
        "finetune",
        f"checkpoint={bc_checkpoint}",
        f"data_dir={data_dir}",
        f"run_dir={run_dir}",
        "finetune.mode=best_of_n",
        "finetune.num_samples=4",
        "finetune.backup=mean",
        "finetune.backup_samples=2",
        "finetune.critic_input=residual",
        "offline.critic_pretrain=2",
        "online.steps=40",
        "online.frames_per_round=40",
        *[o for o in FT if not o.startswith(("online.steps", "online.frames_per_round"))],
    ]
    assert main(args) == 0
    state = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert state["progress"]["offline_updates"] == 6 and state["progress"]["env_steps"] == 40
    metrics = json.loads((run_dir / "history.json").read_text())["history"]["metrics"]
    assert not any("loss_actor" in m for m in metrics)
    saved = yaml.safe_load((run_dir / "config.yaml").read_text())["finetune"]
    assert (saved["backup"], saved["backup_samples"], saved["critic_input"]) == ("mean", 2, "residual")
    bc_weights = load_checkpoint(bc_checkpoint)["ema"]
    inner = {k.removeprefix("actor."): v for k, v in state["model"].items() if k.startswith("actor.")}
    assert inner and all(torch.equal(v, bc_weights[k]) for k, v in inner.items())  # the BC network, untouched
    actor, cfg = load_actor(run_dir / "checkpoints" / "latest.pt")
    assert type(actor).__name__ == "BestOfNActor" and actor.num_samples == 4 and cfg.policy.best_of_n
    assert actor.critic_input == "residual"
    record = json.loads((run_dir / "eval.json").read_text())
    assert record["episodes"] == 2 and 0.0 <= record["success_once"] <= 1.0
    assert (
        main(
            [
                "eval",
                f"checkpoint={run_dir / 'checkpoints' / 'latest.pt'}",
                f"run_dir={tmp_path / 'ev'}",
                "eval.episodes=1",
                "eval.num_envs=1",
                "task.max_episode_steps=30",
            ]
        )
        == 0
    )
    assert json.loads((tmp_path / "ev" / "eval.json").read_text())["episodes"] == 1
