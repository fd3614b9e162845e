"""A fine-tuning algorithm added from outside the library, as a user would: one folder
(``tests/doubles/continued_bc``: loss, settings, ``ALGORITHM``) plus one preset
(``tests/doubles/configs/finetune/continued_bc.yaml``), run end to end through ``l1flow-rl finetune``
on the point-mass double; and the settings block of any algorithm checked at config time."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import torch
from doubles.point_mass import TASK_OVERRIDES, TINY_BC

from l1flow_rl import L1FlowActor
from l1flow_rl.commands.cli import compose_config, main
from l1flow_rl.config.validate import ConfigValidationError
from l1flow_rl.finetune.registry import builtin_algorithm_names, get_algorithm
from l1flow_rl.workspace.checkpoint import load_actor, load_checkpoint

CONFIGS = str(Path(__file__).parents[2] / "doubles" / "configs")
PLUGIN = ["--config-dir", CONFIGS, "finetune=continued_bc"]

BC = TINY_BC
# 3 offline updates, then 2 rounds of 60 env steps (2 envs), 0.05 updates per env step (the preset has
# no warm-up): 3 + 6
FINETUNE = [
    *TASK_OVERRIDES,
    "offline.steps=3",
    "online.steps=120",
    "online.num_envs=2",
    "online.frames_per_round=60",
    "online.updates_per_step=0.05",
    "finetune.batch_size=16",
    "eval.episodes=2",
    "eval.num_envs=1",
    "device=cpu",
]


@pytest.fixture(scope="module")
def bc_checkpoint(tmp_path_factory):
    data_dir, run_dir = tmp_path_factory.mktemp("demos"), tmp_path_factory.mktemp("bc") / "run"
    assert main([*BC, f"data_dir={data_dir}", f"run_dir={run_dir}"]) == 0
    return data_dir, run_dir / "checkpoints" / "latest.pt"


def test_an_algorithm_outside_the_library_is_one_folder_plus_one_preset_and_runs_end_to_end(
    tmp_path, bc_checkpoint
):
    data_dir, checkpoint = bc_checkpoint
    run_dir = tmp_path / "ft"
    args = ["finetune", *PLUGIN, f"checkpoint={checkpoint}", f"data_dir={data_dir}", f"run_dir={run_dir}"]
    assert main([*args, *FINETUNE]) == 0
    state = load_checkpoint(run_dir / "checkpoints" / "latest.pt")
    assert state["progress"] == {
        "offline_updates": 3,
        "online_updates": 6,
        "env_steps": 120,
        "rounds": 2,
        "started": True,
    }
    # the run recorded the block with its defaults, and the checkpoint rebuilds the acting module
    assert state["config"]["policy"]["finetune"]["algorithm"] == "doubles.continued_bc"
    assert state["config"]["finetune"]["continued_bc"] == {"weight": 1.0}
    actor, _ = load_actor(run_dir / "checkpoints" / "latest.pt")
    assert isinstance(actor, L1FlowActor)  # its acting module is the trained flow
    bc = load_checkpoint(checkpoint)
    assert any(not torch.equal(v, bc["ema"][k]) for k, v in state["model"].items())  # updates ran
    logged = (run_dir / "logs" / "finetune" / "scalars" / "offline" / "loss_bc.csv").read_text()
    assert [float(line.split(",")[1]) > 0 for line in logged.split()] == [True]  # at the phase's end
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["episodes"] == 2 and result["split"] == "test"
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["algorithm"] == "doubles.continued_bc" and summary["online_updates"] == 6
    # l1flow-rl eval takes the checkpoint as any other: the registry imports the algorithm by its path
    out = tmp_path / "eval"
    ckpt = run_dir / "checkpoints" / "latest.pt"
    assert main(["eval", *TASK_OVERRIDES, f"checkpoint={ckpt}", "eval.episodes=1", f"run_dir={out}"]) == 0
    assert json.loads((out / "eval.json").read_text())["episodes"] == 1


def test_the_plugin_preset_composes_and_its_settings_are_checked_at_config_time():
    cfg = compose_config([*PLUGIN[2:], "checkpoint=bc.pt"], command="finetune", config_dir=CONFIGS)
    assert cfg.finetune.algorithm == "doubles.continued_bc" and cfg.finetune.continued_bc.weight == 1.0
    assert "continued_bc" not in builtin_algorithm_names() and get_algorithm("doubles.continued_bc").name
    bad = [
        ("finetune.continued_bc.weight=0", r"finetune\.continued_bc\.weight=0\.0: expected > 0"),
        ("finetune.continued_bc.weight=heavy", r"finetune\.continued_bc\.weight='heavy': expected float"),
        ("+finetune.continued_bc.wieght=2", r"finetune\.continued_bc\.wieght: not a setting of continued_bc"),
    ]
    for override, says in bad:
        with pytest.raises(ConfigValidationError, match=says):
            compose_config([*PLUGIN[2:], override], command="finetune", config_dir=CONFIGS)


@pytest.mark.parametrize(
    "override,says",
    [
        ("finetune.qc.num_samples=0", r"finetune\.qc\.num_samples=0: expected >= 1"),
        ("finetune.qc.num_samples=many", r"finetune\.qc\.num_samples='many': expected int"),
        ("finetune.qc.num_sample=8", r"finetune\.qc\.num_sample: not a setting of qc; its settings: "),
        ("finetune.fql.alpha=-1", r"finetune\.fql\.alpha=-1\.0: expected >= 0"),  # another's block: checked
        ("finetune.lrr=0.1", r"finetune\.lrr: not a fine-tuning setting"),
        ("finetune.algorithm=no_such.module", r"finetune\.algorithm='no_such\.module': no module 'no_such'"),
        ("finetune.algorithm=json", r"finetune\.algorithm='json': expected one of \['dsrl', "),
        ("finetune.algorithm=doubles.point_mass", r"module 'doubles\.point_mass' defines no ALGORITHM"),
    ],
)
def test_a_bad_algorithm_or_setting_fails_at_config_time_in_one_line(override, says):
    with pytest.raises(ConfigValidationError, match=says) as err:
        compose_config(["finetune=qc", override], command="finetune")
    assert len(str(err.value).splitlines()) == 2  # the header and one line


def test_every_built_in_algorithm_has_a_folder_a_preset_and_ranges_on_its_numbers():
    from l1flow_rl.config.paths import CONFIG_DIR
    from l1flow_rl.config.ranges import declared_ranges

    names = builtin_algorithm_names()
    assert names == ["dsrl", "dsrl_na", "filtered_bc", "flowq", "fql", "qc"]
    for name in names:
        algorithm = get_algorithm(name)
        assert algorithm.name == name and (Path(CONFIG_DIR) / "finetune" / f"{name}.yaml").is_file()
        numeric = [(key, rng) for key, rng, hint in declared_ranges(algorithm.settings) if hint is not bool]
        assert all(rng is not None for _, rng in numeric), (name, numeric)


def test_a_checkpoint_recording_every_algorithms_block_still_resumes_and_evaluates(tmp_path, bc_checkpoint):
    """Before the per-algorithm folders, a run's config held every algorithm's block (``finetune.qc``,
    ``finetune.fql``, ...); now it holds its own. A checkpoint of that layout resumes (with more env
    steps) and ``load_actor`` rebuilds its acting module."""
    from omegaconf import OmegaConf

    data_dir, checkpoint = bc_checkpoint
    run_dir = tmp_path / "ft"
    short = [a if a != "online.steps=120" else "online.steps=60" for a in FINETUNE]
    args = ["finetune", "finetune=filtered_bc", f"checkpoint={checkpoint}", f"data_dir={data_dir}"]
    assert main([*args, f"run_dir={run_dir}", *short, "eval.enabled=false"]) == 0
    latest = run_dir / "checkpoints" / "latest.pt"
    state = load_checkpoint(latest)
    every = {
        n: OmegaConf.to_container(OmegaConf.structured(get_algorithm(n).settings))
        for n in builtin_algorithm_names()
    }
    assert state["run_config"]["finetune"]["filtered_bc"] == every["filtered_bc"]
    for config in (state["run_config"], state["config"]):
        config["finetune"].update(every)
    state["config"]["policy"]["finetune"].update(every)
    torch.save(state, latest)
    assert isinstance(load_actor(latest)[0], L1FlowActor)
    assert main([*args, f"run_dir={run_dir}", *FINETUNE, "eval.enabled=false", "resume=true"]) == 0
    assert load_checkpoint(latest)["progress"]["env_steps"] == 120


def test_every_declared_range_of_every_built_in_algorithm_is_enforced_at_config_time():
    from l1flow_rl.config.ranges import declared_ranges

    tried = 0
    for name in builtin_algorithm_names():
        for key, rng, _ in declared_ranges(get_algorithm(name).settings, prefix=f"finetune.{name}"):
            for value in [] if rng is None else rng.outside():
                text = f"[{value}]" if rng.each else str(value)
                says = rf"{re.escape(key)}=.*: expected {re.escape(rng.describe())}"
                with pytest.raises(ConfigValidationError, match=says):
                    compose_config([f"finetune={name}", f"{key}={text}"], command="finetune")
                tried += 1
    assert tried >= 8  # num_samples, alpha, noise_bound, init_alpha, distill_samples, hidden dims, ...
