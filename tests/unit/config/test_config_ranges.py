"""Bad input is refused before any work: the composed schema of every command is swept, each numeric
field with values outside its declared range and each path field with an impossible path, and each
must end in one line naming its key, exit code 2, nothing written. A numeric field without a
declared range fails here."""

from __future__ import annotations

import time
import typing

import pytest
from omegaconf import OmegaConf

from l1flow_rl.commands.cli import COMMANDS, main
from l1flow_rl.commands.field_reference import (
    BEGIN,
    END,
    PAGE,
    composed_configs,
    reference_markdown,
    schema_fields,
)
from l1flow_rl.config.app import AppConfig
from l1flow_rl.config.path_fields import DATASET, EXISTING, WRITABLE_DIR, declared_paths
from l1flow_rl.config.ranges import field_range, is_numeric
from l1flow_rl.config.validate import config_problems


@pytest.fixture(scope="module")
def composed():
    """``(command, config)`` for every command, and every fine-tuning preset."""
    return list(composed_configs())


def _numeric_fields(cfg):
    for key, f, hint, value in schema_fields(cfg):
        if is_numeric(hint):
            yield key, field_range(f), value, _holds(hint)


def _holds(hint) -> tuple[bool, bool]:
    """(whether the field holds a list, whether its numbers are integers), e.g. ``list[int] | None``."""
    parts = [hint, *typing.get_args(hint)]
    parts += [a for p in parts for a in typing.get_args(p)]
    return any(typing.get_origin(p) in (list, tuple) for p in parts), int in parts


def test_every_numeric_field_declares_a_range(composed):
    undeclared = {key for _, cfg in composed for key, rng, _, _ in _numeric_fields(cfg) if rng is None}
    assert not undeclared, f"declare a range (bounded(...)) on: {sorted(undeclared)}"
    walked = {key for _, cfg in composed for key, *_ in _numeric_fields(cfg)}
    # each algorithm's own block is walked (its schema named by the algorithm), as are the groups
    assert {"finetune.qc.num_samples", "finetune.fql.alpha", "network.n_groups", "seed"} <= walked


def _outside(rng, value, holds):
    """Values outside the range, shaped as the field holds them (a list field: its first element
    made bad, the length kept)."""
    listed, integer = holds
    for bad in rng.outside():
        if listed:
            items = list(value or []) or [0]
            yield [int(bad) if integer else bad, *items[1:]]
        else:
            yield int(bad) if integer else float(bad)


def test_each_value_outside_its_range_is_refused_naming_the_key(composed):
    swept, seen = 0, set()
    for command, cfg in composed:
        for key, rng, value, holds in list(_numeric_fields(cfg)):
            # a fine-tuning preset differs from another in its algorithm's block only
            if rng is None or ((command, key) in seen and not key.startswith("finetune.")):
                continue
            seen.add((command, key))
            # a range with no bound ("any number", e.g. a target entropy) has no value outside
            original = OmegaConf.to_container(value) if OmegaConf.is_config(value) else value
            for bad in _outside(rng, value, holds):
                OmegaConf.update(cfg, key, bad, merge=False)
                start = time.perf_counter()
                try:
                    problems = config_problems(cfg, command)
                finally:
                    OmegaConf.update(cfg, key, original, merge=False)
                assert time.perf_counter() - start < 1.0, (command, key)
                # the range's line first; any other line a rule about the same key
                assert problems and problems[0].startswith(f"{key}="), (command, key, bad, problems)
                assert all(key in p and "\n" not in p for p in problems), (command, key, bad, problems)
                assert "expected" in problems[0]
                swept += 1
    assert swept > 200  # every command, every field, each bound


def _bad_overrides(cfg, tmp_path):
    """An override outside the range of each declared numeric field, and an impossible path for
    each path field: ``{key: override}``."""
    afile = tmp_path / "a_file"
    afile.write_text("not a directory, not a dataset")
    out = {}
    for key, rng, value, holds in _numeric_fields(cfg):
        if rng is not None:
            bad = next(_outside(rng, value, holds))
            out[key] = f"{key}={bad}"
    for key, rule in declared_paths(AppConfig):
        path = {WRITABLE_DIR: afile / "sub", EXISTING: tmp_path / "missing", DATASET: afile}[rule.kind]
        out[key] = f"{key}={path}"
    return out


@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_bad_value_at_once_is_one_line_each_exit_2_nothing_written(
    command, tmp_path, monkeypatch, capsys
):
    from l1flow_rl.commands.cli import compose_config

    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    cfg = compose_config([], command=command)
    bad = _bad_overrides(cfg, tmp_path)
    start = time.perf_counter()
    assert main([command, *bad.values()]) == 2
    assert time.perf_counter() - start < 20
    lines = capsys.readouterr().err.strip().splitlines()
    assert all(line.startswith(f"l1flow-rl {command}: invalid config: ") for line in lines), lines
    named = {line.split(": invalid config: ", 1)[1].split("=", 1)[0] for line in lines}
    rules = dict(declared_paths(AppConfig))
    expected = {k for k in bad if k not in rules or rules[k].applies_to(command)}
    assert expected <= named, sorted(expected - named)
    assert "Traceback" not in "\n".join(lines)
    assert list(work.iterdir()) == []  # no run directory, no lock, no data
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "work"]


# -- the inputs of issue 70's table, as a user types them ------------------------------------------


@pytest.mark.parametrize(
    ("command", "override", "line"),
    [
        ("train", "train.steps=-5", "train.steps=-5: expected >= 1"),
        ("eval", "checkpoint=CKPT eval.episodes=0", "eval.episodes=0: expected >= 1"),
        ("train", "eval.episodes=0", "eval.episodes=0: expected >= 1"),
        ("finetune", "checkpoint=CKPT eval.episodes=0", "eval.episodes=0: expected >= 1"),
        ("train", "eval.episodes=-3", "eval.episodes=-3: expected >= 1"),
        ("eval", "checkpoint=CKPT eval.enabled=false", "eval.enabled=False: l1flow-rl eval evaluates"),
        ("train", "train.warmup_steps=-10", "train.warmup_steps=-10: expected >= 0"),
        ("train", "train.eval_every=-1", "train.eval_every=-1: expected >= 0"),
        ("train", "train.grad_clip=-1", "train.grad_clip=-1.0: expected >= 0"),
        ("train", "train.batch_size=0", "train.batch_size=0: expected >= 1"),
        ("train", "data_dir=/proc/nope", "data_dir='/proc/nope': cannot create or write in '/proc'"),
        ("train", "run_dir=/proc/nope", "run_dir='/proc/nope': cannot create or write in '/proc'"),
        ("demos", "data_dir=/proc/nope", "data_dir='/proc/nope': cannot create"),
        ("train", "policy.pred_horizon=4", "policy.pred_horizon=4: expected >= policy.obs_horizon - 1 + "),
        ("train", "network.n_groups=0", "network.n_groups=0: expected >= 1"),
        ("train", "network.n_groups=3", "network.down_dims=[64, 128, 256]: every width must be divisible"),
        (
            "train",
            "network.down_dims=[32,64] policy.pred_horizon=15",
            "policy.pred_horizon=15: must be divisible by 2",
        ),
        ("train", "network.kernel_size=4", "network.kernel_size=4: expected an odd number"),
        ("train", "network.timestep_scale=0", "network.timestep_scale=0.0: expected > 0"),
        ("train", "network.timestep_embed_dim=5", "network.timestep_embed_dim=5: expected an even number"),
        (
            "train",
            "task=maniskill_pushcube_rgb encoder.group_size=24",
            "encoder.group_size=24: expected a divisor",
        ),
        ("train", "seed=-1", "seed=-1: expected in [0, 4294967296)"),
        ("toy", "toy.seed=4294967296", "toy.seed=4294967296: expected in [0, 4294967296)"),
        ("demos", "demos.num=0", "demos.num=0: expected >= 1"),
        ("train", "demos.num=0", "demos.num=0: expected >= 1"),
        ("finetune", "checkpoint=CKPT finetune.gamma=1.5", "finetune.gamma=1.5: expected in [0, 1]"),
        ("finetune", "checkpoint=CKPT finetune.tau=2", "finetune.tau=2.0: expected in (0, 1]"),
        (
            "finetune",
            "checkpoint=CKPT finetune.target_critics=3",
            "finetune.target_critics=3: expected at most",
        ),
        (
            "finetune",
            "checkpoint=CKPT online.steps=10 online.frames_per_round=5",
            "online.frames_per_round=5: expected a multiple",
        ),
        ("train", "train.betas=[0.9]", "train.betas=[0.9]: expected two numbers"),
        ("eval", "", "checkpoint=None: eval needs it"),
        ("export", "checkpoint=CKPT", "out=None: export needs it"),
        ("finetune", "checkpoint=missing.pt", "checkpoint='missing.pt': no such file or directory"),
        ("train", "data.path=missing.hdf5", "data.path='missing.hdf5': no such file or directory"),
        ("train", "data.path=CKPT", "data.path='CKPT': not a supported demonstration file"),
        ("train", "encoder.pretrained=missing.pth", "encoder.pretrained='missing.pth': no such file"),
    ],
)
def test_the_issues_inputs_end_in_one_line_naming_the_key(
    command, override, line, tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "CKPT").write_bytes(b"not a checkpoint")
    assert main([command, *override.split()]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"l1flow-rl {command}: invalid config: {line}"), lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["CKPT"]  # nothing written


def test_finetune_refuses_an_rl_horizon_beyond_the_checkpoints_action_steps(tmp_path, monkeypatch, capsys):
    import torch

    from l1flow_rl.commands.cli import compose_config

    monkeypatch.chdir(tmp_path)
    torch.save({"model": {}, "config": {"policy": {"action_steps": 4}}}, tmp_path / "start.pt")
    args = ["finetune", "checkpoint=start.pt"]
    assert main([*args, "finetune.rl_horizon=5"]) == 2
    lines = capsys.readouterr().err.splitlines()
    expected = "finetune.rl_horizon=5: expected at most the checkpoint's policy.action_steps=4"
    assert len(lines) == 1 and expected in lines[0], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["start.pt"]  # nothing written
    assert compose_config([*args[1:], "finetune.rl_horizon=4"], command="finetune").finetune.rl_horizon == 4


def test_without_evaluation_the_seeds_are_not_checked():
    from l1flow_rl.commands.cli import compose_config

    overlapping = ["eval.val_seed=100000"]  # the test seeds' range
    assert not compose_config([*overlapping, "eval.enabled=false"], command="train").eval.enabled
    with pytest.raises(ValueError, match="overlaps the test seeds"):
        compose_config(overlapping, command="train")


def test_debug_shows_the_traceback(tmp_path, monkeypatch):
    from l1flow_rl.config.validate import ConfigValidationError

    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigValidationError, match=r"train\.steps=-5"):
        main(["--debug", "train", "train.steps=-5"])
    assert list(tmp_path.iterdir()) == []


def test_every_problem_is_reported_together_one_line_each(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["train", "train.steps=-5", "seed=-1", "run_dir=/proc/nope", "policy.sampler=rk4"]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert [line.split(": invalid config: ")[1].split("=")[0] for line in lines] == [
        "train.steps",
        "seed",
        "policy.sampler",
        "run_dir",
    ]


def test_defaults_and_presets_lie_inside_their_ranges(composed):
    for command, cfg in composed:
        assert config_problems(cfg, command) == [], command


def test_a_users_dataset_is_recognised_by_its_content(tmp_path):
    from l1flow_rl.data.loading import dataset_problem

    zarr = tmp_path / "demos.zarr"
    zarr.mkdir()
    assert "neither a zarr store nor a LeRobot dataset" in dataset_problem(zarr)
    (zarr / ".zgroup").write_text("{}")
    assert dataset_problem(zarr) is None
    h5py = pytest.importorskip("h5py")
    with h5py.File(tmp_path / "demos.hdf5", "w") as f:
        f.create_group("data")
    assert dataset_problem(tmp_path / "demos.hdf5") is None
    (tmp_path / "torn.hdf5").write_bytes((tmp_path / "demos.hdf5").read_bytes()[:600])
    assert "cannot" in dataset_problem(tmp_path / "torn.hdf5")


def test_the_field_reference_in_docs_cli_is_current():
    text = PAGE.read_text()
    assert BEGIN in text and END in text
    current = text.split(BEGIN, 1)[1].split(END, 1)[0].strip()
    assert current == reference_markdown().strip(), "run: python -m l1flow_rl.commands.field_reference"


def test_numeric_fields_are_told_by_their_type():
    assert all(is_numeric(h) for h in (int, float, int | None, list[int], list[float] | None))
    assert not any(is_numeric(h) for h in (bool, str, str | None, list[str], dict, bool | None))
