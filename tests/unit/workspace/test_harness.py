"""The run harness carries a job that is only its loop: a minimal distillation job (the point-mass
expert's chunks into an L1 Flow actor, pure torch, validated on the point-mass double) resumes
bit-exactly, keeps ``best.pt`` from validation, and writes its summary."""

from __future__ import annotations

import json

import pytest
import torch
from doubles.point_mass import TASK_OVERRIDES
from doubles.point_mass.env import OBS_DIM, expert_action
from tensordict import TensorDict

from l1flow_rl import L1FlowActor, L1FlowLoss
from l1flow_rl.commands.cli import compose_config
from l1flow_rl.errors import RunDirectoryError, RunDivergedError
from l1flow_rl.workspace.checkpoint import ResumeMismatchError, first_non_finite, load_checkpoint
from l1flow_rl.workspace.harness import Run

STEPS, EVERY = 12, 4


def _actor() -> L1FlowActor:
    return L1FlowActor.for_state(OBS_DIM, 2, pred_horizon=8, action_steps=4, down_dims=(8, 16))


def _load_weights(path) -> L1FlowActor:
    """The job's weights from a checkpoint (``best.pt``, when validation chose an earlier step)."""
    actor = _actor()
    actor.load_state_dict(load_checkpoint(path)["model"])
    return actor.eval()


def run_distill(cfg, crash_at: int | None = None, nan_at: int | None = None) -> Run:
    """The whole job: its model, its loop, its state; everything else is the harness's."""
    device = torch.device("cpu")
    with Run(cfg, job="distill", device=device, log_every=2, checkpoint_every=EVERY, eval_every=EVERY) as run:
        actor = _actor()
        loss_fn = L1FlowLoss(actor)
        optim = torch.optim.Adam(actor.parameters(), lr=1e-3)
        step = 0

        def load(state):
            nonlocal step
            actor.load_state_dict(state["model"])
            optim.load_state_dict(state["optimizer"])
            step = state["step"]

        def state():
            return {"model": actor.state_dict(), "ema": None, "optimizer": optim.state_dict(), "step": step}

        run.begin(state, load, step=lambda: step, total=STEPS)
        run.report_for_weights = lambda weights_step: {"weights_trained_steps": weights_step}
        while step < STEPS:
            if step == crash_at:
                raise RuntimeError(f"killed at step {step}")
            obs = torch.rand(16, 2, OBS_DIM) * 2 - 1  # the global RNG: the harness restores it
            chunk = expert_action(obs[:, -1]).unsqueeze(1).expand(16, 8, 2)
            loss = loss_fn(TensorDict({"observation": obs, "action_chunk": chunk}, batch_size=[16]))
            if step == nan_at:  # a term turns NaN (its gradient too): the weights follow
                loss["loss_l1flow"] = loss["loss_l1flow"] * float("nan")
            optim.zero_grad()
            loss["loss_l1flow"].backward()
            optim.step()
            step += 1
            run.step_done(step, {"loss": loss["loss_l1flow"].detach(), "lr": 1e-3}, actor, last=step == STEPS)
        run.finish(actor, {"job": "distill", "steps": step}, load_chosen=_load_weights)
    return run


def _cfg(run_dir, *extra):
    return compose_config(
        [*TASK_OVERRIDES, "eval.episodes=2", "eval.num_envs=2", "device=cpu", f"run_dir={run_dir}", *extra]
    )


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("straight") / "run"
    run_distill(_cfg(run_dir))
    return run_dir


def test_a_minimal_job_keeps_best_from_validation_and_writes_its_summary(straight):
    summary = json.loads((straight / "summary.json").read_text())
    assert summary["job"] == "distill" and summary["steps"] == STEPS and summary["eval_episodes"] == 2
    assert {"train_seconds", "wall_seconds", "cpu_seconds", "machine"} <= set(summary)
    history = json.loads((straight / "history.json").read_text())
    assert history["train"]["step"] == [2, 4, 6, 8, 10, 12]
    val = [e for e in history["evals"] if e["split"] == "val"]
    assert [e["step"] for e in val] == [4, 8, 12]  # on the cadence, and the final model competes
    assert [e["split"] for e in history["evals"]][-1] == "test"
    # best.pt holds the first of the best validation figures; the test figures are its.
    chosen = max(val, key=lambda e: e["success_once"])["step"]
    best = load_checkpoint(straight / "checkpoints" / "best.pt")
    assert best["step"] == chosen
    tested = json.loads((straight / "eval.json").read_text())
    assert tested["selection"]["step"] == chosen
    # what the job reports of the tested weights is of best.pt's step, not of the run's last
    assert tested["weights_trained_steps"] == summary["weights_trained_steps"] == chosen
    latest = load_checkpoint(straight / "checkpoints" / "latest.pt")
    assert latest["step"] == STEPS and latest["config"]["run_dir"] == str(straight)
    assert (straight / "config.yaml").is_file() and (straight / "loss.png").is_file()


def test_a_minimal_job_resumes_where_an_uninterrupted_run_ends(tmp_path, straight):
    run_dir = tmp_path / "run"
    with pytest.raises(RuntimeError, match="killed at step 6"):
        run_distill(_cfg(run_dir), crash_at=6)
    assert load_checkpoint(run_dir / "checkpoints" / "latest.pt")["step"] == EVERY
    with pytest.raises(RunDirectoryError, match="already holds a run"):
        run_distill(_cfg(run_dir))
    with pytest.raises(ResumeMismatchError, match="seed: checkpoint has 0, config asks for 1"):
        run_distill(_cfg(run_dir, "resume=true", "seed=1"))

    run_distill(_cfg(run_dir, "resume=true"))
    resumed = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    whole = load_checkpoint(straight / "checkpoints" / "latest.pt")
    assert [k for k in whole["model"] if not torch.equal(whole["model"][k], resumed["model"][k])] == []
    assert resumed["history"] == whole["history"]
    assert [e["success_once"] for e in resumed["evals"]] == [e["success_once"] for e in whole["evals"]]


def test_a_nan_stops_the_job_at_the_next_read_and_never_reaches_a_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    # Step 7's loss is NaN: metrics are read at step 8 (log_every=2), after validation (step 4)
    # wrote best.pt and the cadence wrote latest.pt.
    with pytest.raises(RunDivergedError, match=r"^distill diverged: at step 8 loss=nan") as info:
        run_distill(_cfg(run_dir), nan_at=6)
    assert f"{run_dir / 'checkpoints' / 'latest.pt'}, is from step 4 and finite" in str(info.value)
    for name in ("latest.pt", "best.pt"):
        state = load_checkpoint(run_dir / "checkpoints" / name)
        assert state["step"] == 4 and first_non_finite(state) is None, name


@pytest.mark.parametrize(
    "name", ["l1flow_rl.errors", "l1flow_rl.workspace.run_lock", "l1flow_rl.workspace.checkpoint"]
)
def test_docstring_examples_run(name):
    import doctest
    import importlib

    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0
