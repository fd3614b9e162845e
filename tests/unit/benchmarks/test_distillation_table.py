"""The paper's second table end to end on the point-mass double: a distillation grid's teachers (EDM,
DDPM), its students from each seed's own teacher (``configs/distill/``), the teachers and CP at the
paper's other step counts (``configs/rescore/``), and L1 Flow's grid, collected by
``bench_distillation`` into one row per method and NFE with the training its weights went through,
the teacher's counted, and a batch-1 latency timed against L1 Flow's in the same run."""

from __future__ import annotations

import json
from pathlib import Path

import doubles.point_mass  # noqa: F401  registers the simulator and its expert
import pytest

from benchmarks.success import bench_distillation
from l1flow_rl.commands.cli import main

CONFIGS = str(Path(__file__).parents[2] / "doubles" / "configs")
STUDENT = ["train.steps=10", "train.eval_every=10", "train.checkpoint_every=10"]


@pytest.fixture(scope="module")
def grids(tmp_path_factory):
    root = tmp_path_factory.mktemp("distillation")
    grid, l1 = root / "grid", root / "l1flow"
    common = ["--config-dir", CONFIGS, "+grid=distillation_point_mass", f"data_dir={root / 'data'}"]
    here = [*common, f"hydra.sweep.dir={grid}"]
    assert main(["train", "-m", *here]) == 0  # the teachers
    for distill in ("cp", "onedp_edm", "onedp_ddpm"):
        assert main(["train", "-m", *here, f"+distill={distill}", *STUDENT]) == 0
    for rescore in ("ddim_steps", "edm_steps", "cp3"):
        assert main(["eval", "-m", *here, f"+rescore={rescore}"]) == 0
    assert main(["train", "-m", *common, "policy=l1flow", f"hydra.sweep.dir={l1}"]) == 0
    return root, grid, l1


def test_every_row_of_the_papers_table_with_its_nfe_training_and_latency(grids, capsys):
    root, grid, l1 = grids
    out = root / "results"
    assert bench_distillation.main([str(grid), str(l1), "--out-dir", str(out), "--rounds", "2"]) == 0
    saved = json.loads((out / "distillation_point_mass_reach.json").read_text())
    rows = saved["rows"]
    assert list(rows) == [row.label for row in bench_distillation.ROWS] and saved["missing_rows"] == []
    nfe = [r["nfe"] for r in rows.values()]
    assert nfe == [100, 10, 1, 35, 19, 1, 3, 1, 1, 1, 1, 1, 2]
    for label, r in rows.items():
        assert r["success_once"]["n"] == 1 and r["per_seed"][0]["episodes"] == 2
        assert r["latency_batch1_ms"]["wall_ms"] > 0
        student = label.startswith(("consistency", "onedp"))
        # a student's weights went through its teacher's shipped checkpoint and its own 10 steps
        (teacher,) = r["teacher_steps"]
        assert teacher in ((10, 20) if student else (0,))  # the step of the teacher's best.pt
        assert r["training_steps"] == [teacher + (10 if student else 20)]
    for label in ("consistency", "onedp_d", "onedp_s", "onedp_d_ddpm", "onedp_s_ddpm"):
        row = rows[label]
        (own,), (teacher,) = row["steps_to_90pct_of_best"], row["teacher_steps"]
        assert row["steps_to_90pct_of_best_with_teacher"] == [None if own is None else teacher + own]
    assert rows["consistency_cp3"]["steps_to_90pct_of_best_with_teacher"] == []  # a re-scoring: no curve
    assert rows["l1flow"]["latency_vs_l1flow"] == 1.0
    assert rows["onedp_d_ddpm"]["method"] == "OneDP-D (DDPM teacher)"
    assert {"edm", "ddpm", "l1flow"} <= set(saved["args"]["policies"]) and saved["args"]["network"] == "unet"
    assert "DP (DDPM) 100" in capsys.readouterr().out


def test_an_unfinished_row_is_refused_unless_partial(grids, tmp_path, capsys):
    _, grid, _ = grids
    # without L1 Flow's grid, its row is missing: refused, then written without it when asked
    assert bench_distillation.main([str(grid), "--out-dir", str(tmp_path), "--rounds", "1"]) == 2
    assert "no finished evaluation for l1flow" in capsys.readouterr().err
    args = [str(grid), "--out-dir", str(tmp_path), "--rounds", "1", "--partial"]
    assert bench_distillation.main(args) == 0
    saved = json.loads((tmp_path / "distillation_point_mass_reach.json").read_text())
    assert saved["missing_rows"] == ["l1flow"] and saved["rows"]["ddpm"]["latency_vs_l1flow"] is None
