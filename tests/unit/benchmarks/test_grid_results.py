"""The results scripts read a grid's folder (hydra's sweep directory of ``l1flow-rl train -m
+grid=...``, re-scorings in ``<run>/rescore_<name>/``): one success file per task with every
method, seed and re-scoring, the grid's setting and its runs' provenance; the ablations file with
every loss variant and sampler swap; an unfinished grid is refused, naming what is missing."""

import json
from pathlib import Path

import yaml
from omegaconf import OmegaConf

from benchmarks.lib.runs import grid_runs
from benchmarks.success import bench_ablations, bench_success
from l1flow_rl.commands.cli import compose_config


def _result(success: float, nfe: float = 2.0, sampler: dict | None = None) -> dict:
    record = {
        "commits": ["a" * 40],
        "launcher": "joblib",
        "resumed_at": [],
        "measured_at": "2026-12-05T00:00:00",
    }
    result = {"success_once": success, "episodes": 100, "ci95": {"success_once": [0.1, 0.9]}}
    result.update(nfe_per_chunk=nfe, split="test", provenance=record, sampler=sampler or {})
    return result


def _job(folder: Path, command: str, num: int, overrides: list[str]) -> None:
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "hydra.yaml").write_text(
        yaml.safe_dump({"hydra": {"job": {"name": command, "num": num}}})
    )
    (folder / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))


def _run(grid: Path, name: str, num: int, overrides: list[str], success: float | None) -> Path:
    """A training job's folder as the harness leaves it (finished when ``success`` is given)."""
    folder = grid / name
    _job(folder, "train", num, overrides)
    OmegaConf.save(compose_config(overrides), folder / "config.yaml")
    if success is not None:
        (folder / "eval.json").write_text(json.dumps(_result(success)))
        evals = [
            {"step": 5, "split": "val", "success_once": success / 2},
            {"step": 10, "split": "val", "success_once": success},
        ]
        (folder / "history.json").write_text(json.dumps({"evals": evals}))
        (folder / "summary.json").write_text(json.dumps({"steps": 10, "cpu_seconds": 5.0}))
    return folder


def _rescore(run: Path, name: str, success: float, sampler: dict | None = None) -> None:
    _job(run / f"rescore_{name}", "eval", 0, [])
    (run / f"rescore_{name}" / "eval.json").write_text(json.dumps(_result(success, 16.0, sampler)))


def test_a_success_grid_becomes_one_file_per_task_with_its_setting_and_provenance(tmp_path, capsys):
    grid = tmp_path / "grid"
    num = 0
    for task in ("maniskill_pushcube", "maniskill_pickcube"):
        for policy in ("l1flow", "ddpm"):
            for seed in (0, 1):
                overrides = [
                    f"task={task}",
                    f"policy={policy}",
                    f"seed={seed}",
                    "train.steps=3000",
                    "eval.protocol=maniskill",
                    "+grid=g",
                ]
                last = (task, policy, seed) == ("maniskill_pickcube", "ddpm", 1)
                run = _run(
                    grid,
                    f"{task}/{policy}/seed{seed}",
                    num,
                    overrides[:-1],
                    None if last else 0.5 + seed / 10,
                )
                (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
                if policy == "ddpm" and not last:
                    _rescore(run, "ddim16", 0.4)
                num += 1
    out = tmp_path / "out"
    # an unfinished run refuses the grid, naming it; --partial writes what is finished
    assert bench_success.main([str(grid), "--out-dir", str(out)]) == 2
    assert "maniskill_pickcube/ddpm/seed1 (training)" in capsys.readouterr().err and not out.exists()
    assert bench_success.main([str(grid), "--out-dir", str(out), "--partial"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["success_pickcube.json", "success_pushcube.json"]

    saved = json.loads((out / "success_pushcube.json").read_text())
    block = saved["tasks"]["maniskill_pushcube"]
    assert set(block) == {"l1flow", "ddpm", "ddpm_ddim16"}
    assert block["l1flow"]["success_once"]["mean"] == 0.55 and block["l1flow"]["success_once"]["n"] == 2
    assert (
        block["ddpm_ddim16"]["per_seed"][0]["nfe_per_chunk"] == 16.0 and block["ddpm_ddim16"]["curves"] == []
    )
    assert block["l1flow"]["curves"][1] == [[5, 0.3], [10, 0.6]]
    args = saved["args"]
    assert (args["demos"], args["steps"], args["seeds"], args["eval_episodes"]) == (100, 3000, [0, 1], 100)
    assert args["extra"] == ["eval.protocol=maniskill"]  # what the grid changes from the defaults
    runs = saved["provenance"]["runs"]
    assert runs["commits"] == ["a" * 40] and runs["launchers"] == ["joblib"] and runs["without_commit"] == 0
    assert (
        runs["command"]
        == "l1flow-rl train -m task=maniskill_pushcube train.steps=3000 eval.protocol=maniskill +grid=g"
    )
    assert runs["swept"]["policy.name"] == ["ddpm", "l1flow"] and runs["swept"]["seed"] == [0, 1]
    assert runs["config"]["eval"]["protocol"] == "maniskill"
    assert saved["provenance"]["command"].startswith("python -m benchmarks.success.bench_success")
    # the report reads it as every success file: the table, its setting, the runs' commit
    from benchmarks.report.success import render_success
    from benchmarks.report.tables import source_line

    assert "| `success_pushcube.json` | maniskill_pushcube | ddpm_ddim16 |" in render_success(
        [("success_pushcube.json", saved)]
    )
    line = source_line(out / "success_pushcube.json", saved, tmp_path / "RESULTS.md")
    command = "l1flow-rl train -m task=maniskill_pushcube train.steps=3000 eval.protocol=maniskill +grid=g"
    assert f"runs: `{command}` at commit `aaaaaaaaaaaa` (launcher joblib)" in line


def test_an_ablation_grid_becomes_its_loss_variants_and_sampler_swaps(tmp_path):
    grid = tmp_path / "grid"
    common = ["task=maniskill_pushcube", "demos.num=20", "train.steps=50"]
    num = 0
    for variant, options in (("default", []), ("mse", ["policy.loss_kwargs.loss_type=mse"])):
        for seed in (0, 1):
            run = _run(
                grid, f"{variant}/seed{seed}", num, [*common, f"seed={seed}", *options], 0.5 + seed / 10
            )
            overrides = [f"+grid/ablation={variant}", f"seed={seed}", "+grid=ablations"]
            (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
            if variant == "default":
                _rescore(run, "euler10", 0.2, {"name": "euler", "kwargs": {"steps": 10}})
                _rescore(run, "euler2", 0.3, {"name": "euler", "kwargs": {"steps": 2}})
            num += 1
    assert [r.name for r in grid_runs(grid)] == ["default/seed0", "default/seed1", "mse/seed0", "mse/seed1"]
    assert bench_ablations.main([str(grid), "--out-dir", str(tmp_path)]) == 0
    saved = json.loads((tmp_path / "ablations_maniskill_pushcube_20demos_50steps.json").read_text())
    variants = saved["variants"]
    assert list(variants) == ["default", "mse", "euler2", "euler10"]
    assert variants["mse"]["kind"] == "loss" and variants["mse"]["options"] == [
        "policy.loss_kwargs.loss_type=mse"
    ]
    assert variants["euler2"]["options"] == ["policy.sampler=euler", "policy.sampler_kwargs.steps=2"]
    assert (
        variants["default"]["success_once"]["n"] == 2 and variants["euler10"]["success_once"]["mean"] == 0.2
    )
    assert saved["args"]["task"] == "maniskill_pushcube" and saved["args"]["seeds"] == [0, 1]
    assert (tmp_path / "ablations_maniskill_pushcube_20demos_50steps.png").is_file()


def _unet_file(results: Path, name: str, demos: int, steps: int, seeds: int, extra: list[str]) -> None:
    per_seed = [{"success_once": 0.8, "episodes": 50, "cpu_seconds": 100.0}] * seeds
    block = {"success_once": {"mean": 0.8, "n": seeds}, "per_seed": per_seed, "curves": []}
    args = {"demos": demos, "steps": steps, "eval_episodes": 50, "extra": extra}
    data = {"args": args, "tasks": {"maniskill_pushcube": {"l1flow": block}}}
    (results / name).write_text(json.dumps(data))


def test_the_mlp_grid_is_paired_with_the_unet_file_of_its_data_most_seeds_first(tmp_path, capsys):
    from benchmarks.report.success import render_network_success
    from benchmarks.success import bench_networks

    results, grid = tmp_path / "results", tmp_path / "grid"
    results.mkdir()
    _unet_file(results, "success_a.json", 100, 12000, 1, [])  # fewer seeds, same steps
    _unet_file(results, "success_b.json", 100, 2500, 3, [])  # the one chosen
    _unet_file(results, "success_c.json", 50, 12000, 3, [])  # other data
    _unet_file(results, "success_d.json", 100, 12000, 3, ["network.name=mlp"])  # not the UNet
    common = ["task=maniskill_pushcube", "policy=l1flow", "network=mlp", "train.steps=12000", "demos.num=100"]
    for seed, success in ((0, 0.7), (1, 0.9)):
        run = _run(grid, f"maniskill_pushcube/l1flow/seed{seed}", seed, [*common, f"seed={seed}"], success)
        _rescore(run, "last_weights", success - 0.1)
    out = tmp_path / "out"
    assert bench_networks.main([str(grid), "--results", str(results), "--out-dir", str(out)]) == 0
    task = json.loads((out / "network_success.json").read_text())["tasks"]["maniskill_pushcube"]
    assert task["unet"]["file"] == "success_b.json"
    assert task["mlp"]["l1flow"]["success_once"]["mean"] == 0.8
    assert task["mlp"]["l1flow_last_weights"]["success_once"]["mean"] == 0.7
    text = render_network_success({"tasks": {"maniskill_pushcube": task}})
    assert "inside the UNet's 95 % interval on 1, above it on 0 and below it on 0 of 1 tasks" in text
    row = text.splitlines()[2]
    # 0.8 over the MLP's 200 episodes lies in the UNet's pooled interval (0.8 over 150 episodes)
    assert row.startswith("| maniskill_pushcube | 100 | 0.800 [0.73, 0.86] (2,500 steps, 3 seeds × 50;")
    assert row.endswith("| 0.700 [0.63, 0.76] | inside | – / 10 (every – / 500) | 100 / 5 |")

    # runs on the UNet are not an MLP grid; a task without the UNet's figures is refused
    assert bench_networks.main([str(grid), "--results", str(tmp_path / "none"), "--out-dir", str(out)]) == 2
    assert "no published UNet L1 Flow figures with 100 demos" in capsys.readouterr().err
    unet = tmp_path / "unet"
    _run(unet, "maniskill_pushcube/l1flow/seed0", 0, [*common[:2], "seed=0"], 0.5)
    assert bench_networks.main([str(unet), "--results", str(results), "--out-dir", str(out)]) == 2
    assert "runs not on network=mlp: maniskill_pushcube/l1flow/seed0" in capsys.readouterr().err


def test_a_network_choice_reads_as_one_override_and_a_field_changed_within_it_as_its_own(tmp_path):
    common = ["task=maniskill_pushcube", "policy=l1flow", "network=mlp"]
    _run(tmp_path, "a/l1flow/seed0", 0, [*common, "seed=0"], 0.5)
    _run(tmp_path, "a/l1flow/seed1", 1, [*common, "seed=1", "network.hidden_dims=[256,256]"], 0.5)
    runs = grid_runs(tmp_path)
    assert bench_success.grid_extra(runs[:1]) == ["network=mlp"]  # not each network.* field
    assert bench_success.grid_extra(runs[1:]) == ["network=mlp", "network.hidden_dims=[256, 256]"]
    assert bench_success.grid_extra(runs) == ["network=mlp"]  # what the runs share
