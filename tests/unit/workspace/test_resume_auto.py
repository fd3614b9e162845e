"""``resume=auto``, what a grid's jobs run with: a run directory holding this very run, finished, is
skipped; one holding a finished run of another setting (any group, the network's included) is
refused, naming each field; where things live or how they are logged may differ."""

import pytest
from doubles.point_mass import TASK_OVERRIDES
from omegaconf import OmegaConf

from l1flow_rl.commands.cli import compose_config
from l1flow_rl.config.validate import ConfigValidationError
from l1flow_rl.errors import RunDirectoryError
from l1flow_rl.workspace.harness import Run, finished_run


def _cfg(run_dir, *overrides):
    return compose_config([*TASK_OVERRIDES, "device=cpu", f"run_dir={run_dir}", "resume=auto", *overrides])


def _finish(run_dir, cfg):
    """What the harness leaves of a finished run: its config, its figures, its summary last."""
    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / "config.yaml")
    (run_dir / "eval.json").write_text("{}")
    (run_dir / "summary.json").write_text("{}")


def test_a_finished_run_of_the_same_setting_is_skipped_and_one_of_another_refused(tmp_path):
    run_dir = tmp_path / "task" / "l1flow" / "seed0"
    cfg = _cfg(run_dir, "network.down_dims=[16,32]", "demos.num=100")
    assert finished_run(cfg) is None  # nothing there yet: the job starts
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "latest.pt").write_bytes(b"")
    assert Run(cfg, job="train", device="cpu").resume  # interrupted: it continues
    assert not Run(_cfg(tmp_path / "elsewhere"), job="train", device="cpu").resume  # a fresh start
    _finish(run_dir, cfg)
    assert finished_run(cfg) == run_dir / "summary.json"
    # the same run found from another machine: other data and run folders, device, logger
    moved = _cfg(run_dir, "network.down_dims=[16,32]", "demos.num=100", "data_dir=/elsewhere", "device=auto")
    assert finished_run(moved) == run_dir / "summary.json"
    # another setting in the folder is an error, not a result: the network group is compared too
    other = _cfg(run_dir, "network.down_dims=[16]", "demos.num=300")
    with pytest.raises(RunDirectoryError) as info:
        finished_run(other)
    message = str(info.value)
    assert "network.down_dims: the finished run has [16, 32], config asks for [16]" in message
    assert "demos.num: the finished run has 100, config asks for 300" in message
    assert "resume=true" in message  # how to continue it anyway
    # only resume=auto skips: resume=false or true leave the folder to the harness's own rules
    assert finished_run(_cfg(run_dir, "resume=true")) is None
    assert finished_run(_cfg(run_dir, "resume=false")) is None
    # a finished run without its config cannot be told apart
    (run_dir / "config.yaml").unlink()
    with pytest.raises(RunDirectoryError, match=r"no config\.yaml"):
        finished_run(cfg)


def test_resume_takes_false_true_or_auto():
    assert compose_config([*TASK_OVERRIDES, "resume=auto"]).resume == "auto"
    assert compose_config([*TASK_OVERRIDES, "resume=true"]).resume is True
    with pytest.raises(ConfigValidationError, match="resume='sometimes': expected false, true or auto"):
        compose_config([*TASK_OVERRIDES, "resume=sometimes"])
