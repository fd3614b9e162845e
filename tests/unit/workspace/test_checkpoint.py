"""Checkpoints: atomic writes survive a kill, loads are weights_only, mismatches are explained."""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import textwrap
import time

import pytest
import torch

from l1flow_rl import L1FlowActor
from l1flow_rl.workspace.checkpoint import (
    RESUME_MAY_CHANGE,
    CheckpointMismatchError,
    ResumeMismatchError,
    check_compatible,
    check_resumable,
    load_checkpoint,
    load_state_into,
    save_checkpoint,
)
from l1flow_rl.workspace.train import TRAIN_MAY_CHANGE


def _state(value: float) -> dict:
    return {
        "model": {"w": torch.full((3,), value)},
        "config": {"task": {"env_id": "PushCube-v1"}},
        "step": int(value),
    }


def test_round_trip_is_readable_with_weights_only(tmp_path):
    path = save_checkpoint(tmp_path / "ck" / "latest.pt", _state(2.0))
    raw = torch.load(path, weights_only=True)  # what any user can do safely
    assert torch.equal(raw["model"]["w"], torch.full((3,), 2.0))
    assert load_checkpoint(tmp_path / "ck")["step"] == 2  # a folder means its latest.pt
    assert [p.name for p in path.parent.iterdir()] == ["latest.pt"]  # no temp files left


class _Payload:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def test_arbitrary_pickles_are_refused(tmp_path):
    path = tmp_path / "evil.pt"
    with open(path, "wb") as f:
        pickle.dump({"model": _Payload(), "config": {}}, f)
    with pytest.raises(ValueError, match="cannot be read safely"):
        load_checkpoint(path)


def test_missing_and_foreign_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nothere\.pt"):
        load_checkpoint(tmp_path / "nothere.pt")
    torch.save({"weights": torch.zeros(1)}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="no 'model' entry"):
        load_checkpoint(tmp_path / "foreign.pt")
    (tmp_path / "torn.pt").write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(ValueError, match=r"torn\.pt"):
        load_checkpoint(tmp_path / "torn.pt")


def test_kill_during_write_keeps_the_previous_checkpoint(tmp_path):
    path = tmp_path / "latest.pt"
    save_checkpoint(path, _state(1.0))
    # A second process writes a large checkpoint to the same path; kill it mid-write.
    script = textwrap.dedent(
        f"""
        import torch
        from l1flow_rl.workspace.checkpoint import save_checkpoint
        big = {{"model": {{"w": torch.zeros(200_000_000)}}, "config": {{}}, "step": 2}}
        save_checkpoint({str(path)!r}, big)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script])
    deadline = time.time() + 300  # the child imports torch first: >60 s on 2 loaded cores (seen)
    while time.time() < deadline and not any(p.name.endswith(".tmp") for p in tmp_path.iterdir()):
        time.sleep(0.01)
    assert any(p.name.endswith(".tmp") for p in tmp_path.iterdir()), "the writer never started its temp file"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    state = load_checkpoint(path)
    assert state["step"] == 1
    assert torch.equal(state["model"]["w"], torch.full((3,), 1.0))


def test_config_mismatch_lists_every_difference():
    saved = {"task": {"env_id": "PushCube-v1", "obs_mode": "state"}, "policy": {"down_dims": [64, 128, 256]}}
    asked = {"task": {"env_id": "PickCube-v1", "obs_mode": "state"}, "policy": {"down_dims": [32, 64]}}
    with pytest.raises(CheckpointMismatchError) as info:
        check_compatible(saved, asked, "runs/x/latest.pt")
    msg = str(info.value)
    assert "task.env_id: checkpoint has 'PushCube-v1', config asks for 'PickCube-v1'" in msg
    assert "network.down_dims" in msg  # a config from before the network group, read in today's layout
    assert "task.obs_mode" not in msg


def test_timestep_scale_is_part_of_a_checkpoints_identity_and_defaults_to_raw_time():
    before = {"policy": {"down_dims": [64, 128, 256]}}  # a checkpoint from before the field
    check_compatible(
        before, {"network": {"name": "unet", "down_dims": [64, 128, 256], "timestep_scale": 1.0}}
    )
    with pytest.raises(
        CheckpointMismatchError, match=r"network\.timestep_scale: checkpoint has 1\.0, config asks for 1000"
    ):
        check_compatible(
            before, {"network": {"name": "unet", "down_dims": [64, 128, 256], "timestep_scale": 1000}}
        )
    with pytest.raises(
        CheckpointMismatchError, match=r"network\.name: checkpoint has 'unet', config asks for 'mlp'"
    ):
        check_compatible(before, {"network": {"name": "mlp", "hidden_dims": [64, 64]}})


def test_loading_weights_into_another_network_says_what_differs():
    small = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32))
    other = L1FlowActor.for_state(obs_dim=7, action_dim=2, down_dims=(16, 32))
    with pytest.raises(CheckpointMismatchError, match=r"shape mismatches") as info:
        load_state_into(other, small.state_dict(), "ck.pt")
    assert "obs_normalizer" in str(info.value) or "film" in str(info.value)
    deeper = L1FlowActor.for_state(obs_dim=5, action_dim=2, down_dims=(16, 32, 64))
    with pytest.raises(CheckpointMismatchError, match=r"not in model|missing from checkpoint"):
        load_state_into(small, deeper.state_dict())


def _train_config(**changes):
    from omegaconf import OmegaConf

    from l1flow_rl.commands.cli import compose_config

    cfg = compose_config(["run_dir=runs/x"])
    for key, value in changes.items():
        OmegaConf.update(cfg, key, value, merge=False)
    return cfg


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("task.name", "maniskill_pickcube"),  # the dataset
        ("task.env_id", "PickCube-v1"),
        ("demos.num", 7),
        ("demos.seed", 3),
        ("data.path", "/data/mine.hdf5"),
        ("seed", 5),
        ("train.steps", 9999),  # the schedule
        ("train.batch_size", 8),
        ("train.lr", 0.5),
        ("train.warmup_steps", 3),
        ("policy.loss", "regression"),  # the loss and its options
        ("policy.loss_kwargs.loss_type", "mse"),
        ("policy.sampler_kwargs.t_first", 0.25),
        ("network.down_dims", [8, 16]),  # the network
        ("network.name", "mlp"),
    ],
)
def test_resume_refuses_a_changed_dataset_schedule_or_loss_naming_the_field(field, value):
    from omegaconf import OmegaConf

    saved = OmegaConf.to_container(_train_config(), resolve=True)
    with pytest.raises(ResumeMismatchError, match=rf"^resume=true: .*\n  {field}: checkpoint has ") as info:
        check_resumable(saved, _train_config(**{field: value}), "runs/x/checkpoints/latest.pt")
    assert str(info.value).count("checkpoint has") == 1  # only the changed field is named
    assert "runs/x/checkpoints/latest.pt" in str(info.value)
    assert isinstance(info.value, CheckpointMismatchError)


def test_resume_accepts_changes_to_evaluation_logging_and_cadence():
    from omegaconf import OmegaConf

    saved = OmegaConf.to_container(_train_config(), resolve=True)
    allowed = {
        "eval.episodes": 3,
        "eval.num_envs": 1,
        "train.log_every": 1,
        "train.checkpoint_every": 7,
        "train.eval_every": 11,
        "train.logger": "tensorboard",
        "task.max_episode_steps": 300,
        "device": "cpu",
        "data_dir": "elsewhere",
        "run_dir": "runs/y",
        "resume": True,
    }
    check_resumable(saved, _train_config(**allowed), "latest.pt", TRAIN_MAY_CHANGE)
    allowing = (*RESUME_MAY_CHANGE, *TRAIN_MAY_CHANGE)
    for key in allowed:  # each one is allowed by a list (every job's, or train's), not by accident
        assert any(key == p or (p.endswith(".*") and key.startswith(p[:-1])) for p in allowing), key
    # The cadences are train's to allow: a job that does not list them refuses their change.
    with pytest.raises(ResumeMismatchError, match=r"train\.log_every"):
        check_resumable(saved, _train_config(**{"train.log_every": 1}), "latest.pt")
    # A field the checkpoint predates is not compared; one it records must still match.
    del saved["data"]["padding"]
    check_resumable(saved, _train_config(**{"data.padding": "diffusion_policy"}), "latest.pt")
