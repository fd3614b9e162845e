"""The CLI's config layer: composition, validation before any work, --cfg job and --help."""

from __future__ import annotations

import pytest

from l1flow_rl.commands.cli import COMMANDS, compose_config, main
from l1flow_rl.config import load_task_config, task_names


def test_default_config_is_the_main_job():
    cfg = compose_config([])
    assert cfg.task.name == "maniskill_pushcube"
    assert cfg.task.obs_mode == "state"
    assert cfg.policy.name == "l1flow"
    assert cfg.policy.sampler == "two_step"
    assert cfg.policy.sampler_kwargs.t_first == 0.5
    assert cfg.demos.num == 100
    assert list(cfg.train.betas) == [0.95, 0.999]
    assert cfg.train.weight_decay == 1e-6
    assert cfg.train.ema_power == 0.75
    assert cfg.eval.episodes >= 50


def test_paper_training_preset():
    cfg = compose_config(["train=paper"])
    assert cfg.train.lr == 1e-4
    assert cfg.train.warmup_steps == 500
    assert cfg.train.batch_size == 64
    assert list(cfg.train.betas) == [0.95, 0.999]
    assert cfg.run_dir.startswith("runs/maniskill_pushcube_l1flow/")


def test_a_task_brings_its_default_budget_and_the_command_line_wins():
    default = compose_config([])
    rgb = compose_config(["task=maniskill_pushcube_rgb"])
    assert (rgb.train.steps, rgb.train.batch_size) == (2000, 32)  # train=cpu_rgb, the task's own budget
    # the main job (maniskill_pushcube): train=cpu_pushcube, cpu's budget with 3,000 steps
    assert (default.train.steps, default.train.batch_size, default.train.eval_every) == (3000, 64, 500)
    assert compose_config(["task=maniskill_pickcube"]).train.steps == 2500  # train=cpu
    assert compose_config(["task=maniskill_pushcube_rgb", "train=gpu_rgb"]).train.steps == 30000
    assert compose_config(["task=maniskill_pushcube_rgb", "train.steps=7"]).train.steps == 7
    # ... and its number of demonstrations
    assert compose_config(["task=maniskill_stackcube"]).demos.num == 300
    assert compose_config(["task=maniskill_stackcube", "demos.num=20"]).demos.num == 20
    assert compose_config(["task=maniskill_stackcube", "demos=default"]).demos.num == 100
    assert default.demos.num == 100 and compose_config(["demos=n300"]).demos.num == 300
    pusht = compose_config(["task=pusht"])  # its budget and demos from its success curve
    assert (pusht.train.steps, pusht.train.eval_every, pusht.demos.num) == (8000, 2000, 200)
    assert load_task_config("maniskill_stackcube").env_id == "StackCube-v1"  # defaults list: not a field


@pytest.mark.parametrize("policy", ["l1flow", "flow", "ddpm", "ddim", "regression"])
def test_every_policy_config_composes(policy):
    cfg = compose_config([f"policy={policy}", "train.steps=7"])
    assert cfg.policy.name == policy
    assert cfg.train.steps == 7


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("train.stepz=3", "stepz"),
        ("train.steps=abc", "train.steps"),
        ("task=no_such_task", "task/no_such_task"),
        ("network.down_dims=12", "network.down_dims"),
        ("policy.down_dims=[32,64,128]", "moved to network.down_dims"),
        ("eval.episodes=[1]", "eval.episodes"),
    ],
)
def test_bad_override_fails_before_work_and_names_the_key(override, message, capsys):
    assert main(["train", override]) == 2
    err = capsys.readouterr().err
    assert "invalid config" in err
    assert message in err


def test_cfg_job_prints_composed_config(capsys):
    assert main(["train", "policy=ddim", "train.steps=11", "--cfg", "job"]) == 0
    out = capsys.readouterr().out
    assert "sampler: ddim" in out
    assert "steps: 11" in out


def test_help_lists_every_subcommand(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert f"  {name} " in out
    assert main(["frobnicate"]) == 2


def test_task_configs_are_valid_and_fit_their_demos():
    names = task_names()
    for required in (
        "maniskill_pushcube",
        "maniskill_pickcube",
        "maniskill_stackcube",
        "maniskill_peginsertion",
        "maniskill_pickcube_rgb",
    ):
        assert required in names
    for name in names:
        task = load_task_config(name)
        assert task.name == name
        # ManiSkill's default limits cut demonstrations short (PickCube demos need 74-88 steps).
        assert task.max_episode_steps >= 100
    with pytest.raises(ValueError, match="unknown task 'nope'"):
        load_task_config("nope")


# -- validation before any work ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("policy.sampler=rk4", "policy.sampler='rk4': expected one of ['ddim', 'ddpm', 'direct'"),
        ("policy.loss=huber", "policy.loss='huber': expected one of ['consistency', 'diffusion', 'edm'"),
        ("policy.normalizer=minmax", "policy.normalizer='minmax': expected one of ['gaussian', 'identity'"),
        ("policy.obs_normalizer=x", "policy.obs_normalizer='x': expected one of"),
        ("train.logger=mlflow", "train.logger='mlflow': expected one of ['csv', 'tensorboard', 'wandb']"),
        (
            "eval.protocol=robomimic",
            "eval.protocol='robomimic': expected one of ['default', 'diffusion_policy', 'maniskill'",
        ),
        ("encoder=state task=maniskill_pickcube_rgb", "encoder.name='state' reads flat vectors only"),
        ("encoder.name=vit", "encoder.name='vit': expected one of"),
        ("task.simulator=isaac", "task.simulator='isaac': expected one of ['maniskill'"),
        ("task.control=relative", "task.control='relative': expected one of ['absolute', 'delta']"),
        ("task.obs_mode=depth", "task.obs_mode='depth': simulator 'maniskill' supports"),
        ("data.padding=zeros", "data.padding='zeros': expected one of ['diffusion_policy', 'maniskill']"),
        ("+policy.sampler_kwargs.steps=4", "policy.sampler_kwargs.steps: sampler 'two_step' takes no such"),
        ("policy.sampler_kwargs.t_first=1.5", "t_first must lie strictly inside (0, 1)"),
        (
            "policy.loss_kwargs.loss_typ=l1",
            "policy.loss_kwargs.loss_typ: loss 'l1flow' (L1FlowLoss) takes no",
        ),
        ("policy.loss_kwargs.timesteps=gauss", "policy.loss_kwargs.timesteps: unknown timestep distribution"),
        (
            "policy.sampler=ddim ~policy.sampler_kwargs.t_first",
            "policy.sampler='ddim' reads a 'epsilon'-prediction network, but policy.loss='l1flow' "
            "trains 'sample' prediction; samplers that fit: ['euler', 'two_step']",
        ),
        ("policy.sampler=euler", "t_first: sampler 'euler' takes no such argument; it takes ['steps'] (drop"),
    ],
)
def test_bad_values_fail_before_any_work_naming_field_and_choices(
    override, message, capsys, tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)  # nothing may be written: no run directory, no demonstrations
    assert main(["train", *override.split(), f"data_dir={tmp_path / 'data'}"]) == 2
    err = capsys.readouterr().err
    assert "invalid config" in err
    assert message in err, err
    assert list(tmp_path.iterdir()) == []


def test_every_problem_is_listed_at_once():
    from l1flow_rl.config.validate import ConfigValidationError

    with pytest.raises(ConfigValidationError, match=r"^3 config value\(s\) cannot work") as info:
        compose_config(["policy.sampler=rk4", "train.logger=x", "data.padding=z"])
    assert [line.split("=")[0].strip() for line in str(info.value).splitlines()[1:]] == [
        "data.padding",
        "policy.sampler",
        "train.logger",
    ]


def test_eval_does_not_check_the_command_lines_method():
    # eval takes the method from its checkpoint and applies only the sampler given on the command
    # line (it checks that swap itself), so the default policy's loss must not veto a DDIM sampler.
    cfg = compose_config(["policy.sampler=ddim", "policy.sampler_kwargs.steps=16"], command="eval")
    assert (cfg.policy.sampler, cfg.policy.sampler_kwargs.steps) == ("ddim", 16)


# -- hydra application: run directories, record of overrides, sweeps, HydraConfig -----------------

_SEEN: list[dict] = []


def probe(cfg) -> int:
    """A sub-command for these tests: records what a command sees while it runs."""
    from hydra.core.hydra_config import HydraConfig

    from l1flow_rl.config.overrides import user_overrides

    _SEEN.append(
        {
            "run_dir": cfg.run_dir,
            "output_dir": HydraConfig.get().runtime.output_dir,
            "overrides": user_overrides(),
            "seed": cfg.seed,
            "policy": cfg.policy.name,
        }
    )
    return 3 if cfg.seed == 13 else 0


@pytest.fixture
def probe_command(monkeypatch, tmp_path):
    monkeypatch.setitem(COMMANDS, "probe", (__name__, "probe", "test probe"))
    monkeypatch.chdir(tmp_path)
    _SEEN.clear()
    return _SEEN


def test_default_run_dir_is_unique_per_run_and_records_the_overrides(probe_command, tmp_path):
    import time

    import yaml

    assert main(["probe", "seed=4"]) == 0
    time.sleep(1.1)  # run directories are stamped to the second
    assert main(["probe", "seed=4"]) == 0
    first, second = probe_command
    assert first["run_dir"] != second["run_dir"]
    for seen in (first, second):
        run_dir = tmp_path / seen["run_dir"]
        assert seen["run_dir"].startswith("runs/maniskill_pushcube_l1flow/")  # relative to the cwd
        assert str(run_dir) == seen["output_dir"]
        assert seen["overrides"] == ["seed=4"]  # HydraConfig is set while the command runs
        assert yaml.safe_load((run_dir / ".hydra" / "overrides.yaml").read_text()) == ["seed=4"]
        assert yaml.safe_load((run_dir / ".hydra" / "config.yaml").read_text())["seed"] == 4
    assert main(["probe", "seed=13"]) == 3  # the command's return value is the exit code


def test_multirun_sweeps_every_combination_in_its_own_folder(probe_command, tmp_path):
    import yaml

    assert main(["probe", "-m", "seed=0,1", "policy=l1flow,ddpm", f"run_dir={tmp_path / 'sweep'}"]) == 0
    assert sorted((s["seed"], s["policy"]) for s in probe_command) == [
        (0, "ddpm"),
        (0, "l1flow"),
        (1, "ddpm"),
        (1, "l1flow"),
    ]
    folders = sorted(p.name for p in (tmp_path / "sweep").iterdir() if p.is_dir())
    assert folders == [
        "0_maniskill_pushcube_l1flow_seed0",
        "1_maniskill_pushcube_ddpm_seed0",
        "2_maniskill_pushcube_l1flow_seed1",
        "3_maniskill_pushcube_ddpm_seed1",
    ]
    for seen in probe_command:
        assert str(tmp_path / seen["run_dir"]) == seen["output_dir"]
        assert seen["run_dir"].startswith("sweep/")  # relative to the working directory
        recorded = yaml.safe_load((tmp_path / seen["run_dir"] / ".hydra" / "overrides.yaml").read_text())
        assert f"seed={seen['seed']}" in recorded and f"policy={seen['policy']}" in recorded
    assert (tmp_path / "sweep" / "multirun.yaml").is_file()


def test_a_sweep_validates_every_job_before_the_first_starts(probe_command, capsys):
    assert main(["probe", "-m", "policy.sampler=two_step,rk4"]) == 2
    assert probe_command == []  # not even the valid first job ran
    assert "policy.sampler='rk4'" in capsys.readouterr().err


def test_command_help_lists_config_groups_and_their_options(capsys):
    assert main(["train", "--help"]) == 0
    out = capsys.readouterr().out
    lines = {line.split()[0]: line for line in out.splitlines() if line.startswith("  ") and line.split()}
    assert "ddim, ddpm, edm, flow, l1flow, onedp_d, onedp_s, regression" in lines["policy"]
    assert "(now: l1flow)" in lines["policy"]
    assert lines["task"].startswith("  task     maniskill_")  # long lists wrap onto indented lines
    assert "maniskill_pushcube," in out and "(now: maniskill_pushcube)" in out
    assert "cpu" in lines["train"] and "paper" in lines["train"]
    assert "-m" in out and "--cfg job" in out
    assert main(["train", "policy=ddpm", "--help"]) == 0  # the choices follow the command line
    assert "(now: ddpm)" in capsys.readouterr().out
