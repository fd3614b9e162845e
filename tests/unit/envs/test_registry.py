"""The simulator registry (envs/registry.py): lookups, refusals and the checks that run before an
env is built. Test simulators are registered under unique names and removed afterwards."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from doubles.point_mass import POINT_MASS_TASK, PointMassEnv, make_point_mass_env
from l1flow_rl.envs import (
    SimulatorNotInstalledError,
    SimulatorSpec,
    get_simulator,
    make_env,
    register_simulator,
    registered_simulators,
    unregister_simulator,
)
from l1flow_rl.envs.registry import builtin_simulator_packages

from l1flow_rl.config import TaskConfig


class FactoryCalls:
    """A factory that records its calls and makes a point mass env (or whatever ``make`` returns)."""

    def __init__(self, make=make_point_mass_env) -> None:
        self.calls, self.make = 0, make

    def __call__(self, task, num_envs, device, **options):
        self.calls += 1
        return self.make(task, num_envs, device, **options)


@pytest.fixture
def register():
    """Register specs for one test; every name registered is removed afterwards."""
    names = []

    def add(name: str, **fields) -> SimulatorSpec:
        fields.setdefault("factory", FactoryCalls())
        fields.setdefault("observation_entries", lambda task: {"observation": 1})
        fields.setdefault("install_hint", f"pip install {name}-sim")
        spec = register_simulator(SimulatorSpec(name=name, **fields))
        names.append(name)
        return spec

    yield add
    for name in names:
        unregister_simulator(name)


def task_for(simulator: str, **fields) -> TaskConfig:
    return dataclasses.replace(POINT_MASS_TASK, simulator=simulator, **fields)


def test_simulator_packages_are_discovered_and_registered():
    packages = builtin_simulator_packages()
    assert "maniskill" in packages and "doubles" not in packages
    known = registered_simulators()
    assert set(packages) <= set(known)  # every package under envs/ registered itself on import
    assert known["point_mass"].options == ("goal_tolerance",)
    assert get_simulator("point_mass").episode_metrics == {"final_distance": ("last", "distance")}


def test_an_unknown_simulator_lists_the_registered_ones():
    with pytest.raises(ValueError, match="unknown simulator 'mujoco_playground'") as err:
        get_simulator("mujoco_playground")
    for name in registered_simulators():
        assert repr(name) in str(err.value)
    with pytest.raises(ValueError, match="unknown simulator 'mujoco_playground'"):
        make_env(task_for("mujoco_playground"))


def test_a_second_registration_under_a_name_is_refused(register):
    first = register("reg_dup")
    with pytest.raises(ValueError, match="simulator named 'reg_dup' is already registered") as err:
        register_simulator(dataclasses.replace(first, install_hint="other"))
    assert "replace=True" in str(err.value)
    assert get_simulator("reg_dup") is first
    # registering the same spec again is harmless; replace=True swaps it
    assert register_simulator(first) is first
    other = register_simulator(dataclasses.replace(first, install_hint="other"), replace=True)
    assert get_simulator("reg_dup") is other
    with pytest.raises(ValueError, match="simulator named 'maniskill' is already registered"):
        register_simulator(dataclasses.replace(first, name="maniskill"))


def test_a_missing_requirement_raises_the_install_hint_before_anything_is_built(register):
    factory = FactoryCalls()
    spec = register("reg_missing", factory=factory, requires=("torch", "no_such_module_l1flow_xyz"))
    assert not spec.is_installed()
    with pytest.raises(SimulatorNotInstalledError) as err:
        make_env(task_for("reg_missing"), num_envs=2)
    message = str(err.value)
    assert "simulator 'reg_missing' needs no_such_module_l1flow_xyz" in message
    assert "pip install reg_missing-sim" in message and "torch" not in message.split("needs")[1].split(",")[0]
    assert isinstance(err.value, ImportError)
    assert factory.calls == 0


def test_options_the_simulator_does_not_take_are_named(register):
    factory = FactoryCalls()
    register("reg_opts", factory=factory, options=("goal_tolerance",))
    with pytest.raises(TypeError, match=r"\[.colour., .friction.\] are neither TaskConfig fields"):
        make_env(task_for("reg_opts"), friction=0.1, colour="red")
    env = make_env(task_for("reg_opts"), goal_tolerance=0.2, max_episode_steps=7)
    assert factory.calls == 1
    assert env.base_env.goal_tolerance == 0.2 and env.base_env.task.max_episode_steps == 7


def test_an_obs_mode_the_simulator_lacks_is_named(register):
    factory = FactoryCalls()
    register("reg_obs", factory=factory, obs_modes=("state",))
    with pytest.raises(ValueError, match=r"obs_mode='rgb': simulator 'reg_obs' supports \['state'\]"):
        make_env(task_for("reg_obs", obs_mode="rgb"))
    assert factory.calls == 0


def test_env_block_keys_are_checked_where_the_simulator_declares_them(register):
    factory = FactoryCalls()
    spec = register("reg_keys", factory=factory, env_keys=("damping",))
    bad = task_for("reg_keys", env={"damping": 0.1, "gravity": 9.8})
    assert spec.task_problems(bad) == [
        "task.env: simulator 'reg_keys' takes no key(s) ['gravity']; it takes ['damping']"
    ]
    with pytest.raises(ValueError, match="takes no key"):
        make_env(bad)
    assert factory.calls == 0
    # env_keys=None: the block goes to the simulator's own constructor unchecked here
    assert register("reg_keys_open").task_problems(bad) == []
    # the double reads its declared key
    assert make_env(task_for("reg_keys", env={"damping": 0.5})).base_env.damping == 0.5


def test_a_factory_that_breaks_the_contract_is_named(register):
    register("reg_batch", factory=lambda task, n, device, **kw: PointMassEnv(task, n + 1, device))
    with pytest.raises(ValueError, match=r"'reg_batch'.*batch size \(3,\), expected \(2,\)"):
        make_env(task_for("reg_batch"), num_envs=2)

    class NoSuccess(PointMassEnv):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            del self.observation_spec["success"]

    register("reg_success", factory=lambda task, n, device, **kw: NoSuccess(task, n, device))
    with pytest.raises(ValueError, match=r"lacks \['success'\]"):
        make_env(task_for("reg_success"))
    register("reg_entries", observation_entries=lambda task: {"observation": 3})
    with pytest.raises(ValueError, match=r"'observation' has shape \(1, 6\); observation_entries says"):
        make_env(task_for("reg_entries"))


def test_a_spec_with_a_bad_episode_metric_is_refused():
    with pytest.raises(ValueError, match=r"episode_metrics\['score'\] must be \(reduction, step entry\)"):
        SimulatorSpec(
            "reg_bad_metric",
            factory=make_point_mass_env,
            observation_entries=lambda task: {"observation": 1},
            install_hint="",
            episode_metrics={"score": ("median", "reward")},
        )


def test_the_registry_imports_no_simulator():
    import subprocess
    import sys

    script = (
        "import sys\n"
        "from l1flow_rl.envs import get_simulator, registered_simulators\n"
        "assert get_simulator('maniskill').obs_modes == ('state', 'rgb')\n"
        "registered_simulators()\n"
        "loaded = [m for m in ('mani_skill', 'sapien', 'robosuite', 'gym_pusht') if m in sys.modules]\n"
        "assert not loaded, loaded\n"
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr


def test_make_env_gives_the_factory_the_generic_arguments(register):
    device = "cpu"
    seen = {}

    def factory(task, num_envs, device, **options):
        seen.update(options, num_envs=num_envs, device=device)
        return make_point_mass_env(task, num_envs, device, **options)

    register("reg_args", factory=factory, options=("goal_tolerance",))
    make_env(task_for("reg_args"), num_envs=3, device=device, render=False, goal_tolerance=0.1)
    assert seen == {
        "num_envs": 3,
        "device": torch.device(device),
        "ignore_terminations": True,
        "render": False,
        "camera": None,
        "goal_tolerance": 0.1,
    }
