"""benchmarks.archive: a sweep's finished runs survive the machine (records in, checkpoints out), and
a sweep reads restored runs and re-scorings back instead of repeating them."""

from __future__ import annotations

import json
import os

import pytest
from omegaconf import OmegaConf

from benchmarks import archive
from benchmarks.sweep import Run, rescore, train

OVERRIDES = ["task=maniskill_pushcube", "policy=l1flow", "seed=0", "demos.num=20"]


def _finished_run(run_dir, success: float) -> None:
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "best.pt").write_bytes(b"\0" * 4096)
    cfg = {
        "task": {"name": "maniskill_pushcube"},
        "policy": {"name": "l1flow"},
        "seed": 0,
        "demos": {"num": 20},
    }
    OmegaConf.save(OmegaConf.create(cfg), run_dir / "config.yaml")
    (run_dir / "eval.json").write_text(json.dumps({"success_once": success}))
    (run_dir / "history.json").write_text(json.dumps({"evals": [{"step": 500, "success_once": success}]}))
    (run_dir / "summary.json").write_text(json.dumps({"cpu_seconds": 450.0}))
    (run_dir / "loss.png").write_bytes(b"png")
    rescored = run_dir / "rescore_euler1"
    rescored.mkdir()
    checkpoint = str(run_dir / "checkpoints" / "best.pt")
    (rescored / "eval.json").write_text(json.dumps({"success_once": success / 2, "checkpoint": checkpoint}))


def test_save_then_restore_brings_back_the_records_but_not_the_checkpoints(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    root = tmp_path / "runs" / "sweep"
    _finished_run(root / "maniskill_pushcube" / "l1flow" / "seed0", 0.7)
    unfinished = root / "maniskill_pushcube" / "l1flow" / "seed1"
    (unfinished / "checkpoints").mkdir(parents=True)
    (unfinished / "checkpoints" / "latest.pt").write_bytes(b"\0")

    written = archive.save(root.relative_to(tmp_path), tmp_path / "arch")
    stored = tmp_path / "arch" / "runs" / "sweep" / "maniskill_pushcube" / "l1flow"
    names = sorted(str(p.relative_to(stored)) for p in written)
    assert names == [
        "seed0/config.yaml",
        "seed0/eval.json",
        "seed0/history.json",
        "seed0/rescore_euler1/eval.json",
        "seed0/summary.json",
    ]
    assert not (stored / "seed1").exists()  # nothing finished there

    for path in sorted(root.rglob("*"), key=lambda p: -len(p.parts)):
        path.unlink() if path.is_file() else path.rmdir()
    restored = archive.restore(root.relative_to(tmp_path), tmp_path / "arch")
    assert len(restored) == 5
    run_dir = root / "maniskill_pushcube" / "l1flow" / "seed0"
    assert not (run_dir / "checkpoints").exists() and not (run_dir / "loss.png").exists()

    # the sweep reads the restored run and its re-scoring back; neither can start a process here
    monkeypatch.setattr("benchmarks.sweep._cli", lambda *a, **k: pytest.fail("the sweep ran a process"))
    run = Run("l1flow", OVERRIDES, run_dir)
    assert run.done and train(run, tmp_path / "data")["success_once"] == 0.7
    assert rescore(run, "euler1", ["policy.sampler=euler"])["success_once"] == 0.35
    with pytest.raises(FileNotFoundError, match=r"no .*best.pt|no .*latest.pt"):
        rescore(run, "ddim16", ["policy.sampler=ddim"])  # a new re-scoring needs the network


def test_restore_keeps_a_live_run_and_refuses_what_it_cannot_place(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    root = tmp_path / "runs" / "sweep"
    run_dir = root / "pushcube" / "seed0"
    _finished_run(run_dir, 0.7)
    archive.save(root.relative_to(tmp_path), tmp_path / "arch")
    (run_dir / "eval.json").write_text(json.dumps({"success_once": 0.9}))  # newer than the record
    os.remove(run_dir / "rescore_euler1" / "eval.json")
    written = archive.restore(root.relative_to(tmp_path), tmp_path / "arch")
    assert [p.as_posix() for p in written] == ["runs/sweep/pushcube/seed0/rescore_euler1/eval.json"]
    assert json.loads((run_dir / "eval.json").read_text())["success_once"] == 0.9

    with pytest.raises(ValueError, match="relative to the repository"):
        archive.save(root, tmp_path / "arch")
    with pytest.raises(FileNotFoundError, match="nothing archived for runs/other"):
        archive.restore(root.parent.relative_to(tmp_path) / "other", tmp_path / "arch")
    with pytest.raises(FileNotFoundError, match="runs/missing: no such sweep root"):
        archive.save(root.parent.relative_to(tmp_path) / "missing", tmp_path / "arch")
