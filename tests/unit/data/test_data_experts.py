"""The demonstration-source registry: dispatch, the errors a user meets, and the contract that an
expert's file is one the data layer reads (a test double registers itself; no simulator runs)."""

from __future__ import annotations

import subprocess
import sys

import h5py
import numpy as np
import pytest
from omegaconf import OmegaConf

from l1flow_rl.config import AppConfig, TaskConfig
from l1flow_rl.data import episodes_metadata, load_episodes
from l1flow_rl.experts import DemoGenerationError, ExpertSpec, ensure_demos, get_expert, register_expert
from l1flow_rl.experts.registry import registered_experts, unregister_expert

CALLS: list[dict] = []


def _make(task, num, data_dir, *, seed=0, **options):
    """A scripted 'expert' writing ``num`` robomimic demos of a 1-D reach (reward 1 at the goal)."""
    CALLS.append({"num": num, "seed": seed, **options})
    path = data_dir / f"{task.env_id}.n{num}.hdf5"
    with h5py.File(path, "w") as f:
        for i in range(num):
            n = 3 + i
            g = f.create_group(f"data/demo_{i}")
            g["obs/pos"] = np.linspace(0, 1, n + 1)[:n, None]
            g["next_obs/pos"] = np.linspace(0, 1, n + 1)[1:, None]
            g["actions"] = np.full((n, 1), options.get("speed", 1.0))
            g["rewards"] = (np.arange(n) == n - 1).astype(np.float32)
            g["dones"] = np.arange(n) == n - 1
    return path


@pytest.fixture
def reach_expert():
    spec = register_expert(
        ExpertSpec(
            simulator="reachsim",
            make=_make,
            description="a scripted 1-D reach",
            env_ids=("Reach-v0",),
            options=("speed", "progress"),
        )
    )
    CALLS.clear()
    yield spec
    unregister_expert("reachsim")


def task(env_id="Reach-v0", simulator="reachsim", **kw) -> TaskConfig:
    return TaskConfig(name="reach", simulator=simulator, env_id=env_id, **kw)


def test_dispatch_reaches_the_registered_expert_and_the_data_layer_reads_its_file(reach_expert, tmp_path):
    assert get_expert(task()) is reach_expert and registered_experts()["reachsim"] is reach_expert
    path = ensure_demos(task(expert={"speed": 0.5}), 2, tmp_path, seed=7, progress=False)
    assert CALLS == [{"num": 2, "seed": 7, "speed": 0.5, "progress": False}]  # task.expert options merged
    ensure_demos(task(expert={"speed": 0.5}), 1, tmp_path, speed=2.0)  # an explicit option wins
    assert CALLS[-1]["speed"] == 2.0
    eps = load_episodes(path)
    assert eps["episode"].unique().tolist() == [0, 1] and eps["action"].unique().tolist() == [0.5]
    meta = episodes_metadata(eps)
    assert meta.has_rewards and meta.has_final_observation
    assert eps["next", "observation"][2, 0].item() == pytest.approx(1.0)  # the final observation, kept


def test_unknown_simulator_names_it_and_the_experts_that_exist(tmp_path):
    with pytest.raises(
        DemoGenerationError, match=r"no expert makes demonstrations for simulator 'nosuchsim'"
    ) as err:
        ensure_demos(task(simulator="nosuchsim"), 1, tmp_path)
    assert "maniskill" in str(err.value) and "data.path" in str(err.value)


def test_unsupported_env_id_names_what_the_expert_solves(reach_expert, tmp_path):
    with pytest.raises(
        DemoGenerationError,
        match=r"the reachsim expert solves \['Reach-v0'\], not 'Push-v0'; point data\.path",
    ):
        ensure_demos(task(env_id="Push-v0"), 1, tmp_path)
    assert CALLS == []


def test_unknown_option_is_refused_by_name_before_any_work(reach_expert, tmp_path):
    with pytest.raises(
        TypeError, match=r"takes no option\(s\) \['sped'\] \(it takes \['speed', 'progress'\]\)"
    ):
        ensure_demos(task(), 1, tmp_path, sped=2.0)
    with pytest.raises(TypeError, match=r"\['colour'\]"):
        ensure_demos(task(expert={"colour": "red"}), 1, tmp_path)  # from the task's expert block too
    assert CALLS == []


def test_a_second_expert_for_one_simulator_is_refused(reach_expert):
    other = ExpertSpec(simulator="reachsim", make=_make, description="another")
    with pytest.raises(ValueError, match="an expert for simulator 'reachsim' is already registered"):
        register_expert(other)
    assert register_expert(other, replace=True) is other


def test_cli_reports_a_missing_expert(capsys, tmp_path):
    from l1flow_rl.commands.demos import run_demos

    cfg = OmegaConf.structured(AppConfig)
    cfg.task.simulator, cfg.data_dir = "nosuchsim", str(tmp_path)
    assert run_demos(cfg) == 1
    assert "no expert makes demonstrations for simulator 'nosuchsim'" in capsys.readouterr().err


def test_builtin_experts_register_without_importing_a_simulator():
    code = (
        "import sys; from l1flow_rl.experts import registered_experts; specs = registered_experts(); "
        "sims = [m for m in ('mani_skill', 'robosuite', 'gym_pusht') if m in sys.modules]; "
        "print('maniskill' in specs, sims)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert out.stdout.split("\n")[0] == "True []"
