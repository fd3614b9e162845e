"""The robosuite adapter on the real simulator: specs, seeds, success, worker envs, install hint."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import check_env_specs

pytest.importorskip("robosuite")
pytestmark = pytest.mark.robosuite

from l1flow_rl.envs import make_env  # noqa: E402
from l1flow_rl.envs.per_env import seeded_reset  # noqa: E402
from l1flow_rl.envs.robosuite import sim  # noqa: E402
from l1flow_rl.envs.robosuite.env import RobosuiteEnv  # noqa: E402

from l1flow_rl.config import load_task_config  # noqa: E402


def test_state_env_passes_check_env_specs_with_robomimic_state():
    task = load_task_config("robosuite_lift", max_episode_steps=4)
    env = RobosuiteEnv(task, render=False)
    check_env_specs(env, seed=0)
    # object (10) + eef pos (3) + eef quat (4) + gripper qpos (2), in the task's order
    obs = env.reset()["observation"]
    raw = env.sim._get_observations(force_update=True)
    keys = ["object-state", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"]
    expected = np.concatenate([raw[k] for k in keys])
    assert obs.shape == (19,) and obs.dtype == torch.float32
    np.testing.assert_allclose(obs.numpy(), expected.astype(np.float32), rtol=0, atol=0)
    td = env.rollout(10)
    assert td.batch_size == (4,) and bool(td["next", "truncated"][-1]) and not td["next", "done"][:-1].any()
    env.close()


def test_image_env_passes_check_env_specs_with_named_upright_cameras():
    task = load_task_config("robosuite_lift_image", max_episode_steps=3)
    env = make_env(task, num_envs=1, render=False)
    check_env_specs(env, seed=0)
    td = env.reset()
    obs = td["observation"]
    assert set(obs.keys()) == {"state", "agentview_image", "robot0_eye_in_hand_image"}
    assert obs["agentview_image"].shape == (1, 2, 3, 84, 84) and obs["agentview_image"].dtype == torch.uint8
    assert obs["state"].shape == (1, 2, 9)
    # upright: the table (bottom rows) and the sky/wall (top rows) differ; robosuite's raw frame is
    # upside down, and the adapter's image is its vertical flip
    base = env.base_env
    raw = base._envs[0].sim._get_observations(force_update=True)["agentview_image"]
    np.testing.assert_array_equal(obs["agentview_image"][0, -1].permute(1, 2, 0).numpy(), raw[::-1])
    env.close()


def test_same_seed_same_scene_and_different_seeds_differ():
    env = make_env("robosuite_can", num_envs=1, render=False, max_episode_steps=5)
    a = seeded_reset(env, None, [11])["observation"].clone()
    env.rollout(3, break_when_any_done=False, auto_reset=False, tensordict=env.reset())
    b = seeded_reset(env, None, [11])["observation"]
    c = seeded_reset(env, None, [12])["observation"]
    assert torch.equal(a, b)
    assert (a - c).abs().max() > 1e-3
    env.close()


class _ReplayChunks(TensorDictModuleBase):
    """Plays fixed actions open loop, K per call (a chunk policy for the shared evaluator)."""

    def __init__(self, actions: np.ndarray, k: int = 8) -> None:
        super().__init__()
        self.in_keys, self.out_keys = ["observation", "is_init"], ["action_chunk"]
        self.actions, self.k, self.t = torch.as_tensor(actions, dtype=torch.float32), k, 0

    def forward(self, td: TensorDict) -> TensorDict:
        if bool(td["is_init"].any()):
            self.t = 0
        idx = torch.arange(self.t, self.t + self.k).clamp(max=len(self.actions) - 1)
        self.t += self.k
        td["action_chunk"] = self.actions[idx].expand(*td.batch_size, self.k, self.actions.shape[-1]).clone()
        return td


def test_success_comes_from_check_success_through_the_shared_evaluator():
    from l1flow_rl.evaluation import evaluate
    from l1flow_rl.experts.robosuite.demos import run_episode

    task = load_task_config("robosuite_lift", max_episode_steps=60)
    raw_env = sim.make_from_env_args(sim.env_args_for_task(task, cameras=[]))
    demo = run_episode(raw_env, task, seed=5)
    assert demo is not None
    env = make_env(task, num_envs=1, render=False)
    replay = evaluate(_ReplayChunks(demo["actions"]), env, episodes=1, seed=5)
    # the open-loop replay of the expert's actions from the same seed lifts the cube ...
    assert replay["success_once"] == 1.0
    # ... and holding the start pose does not
    hold = np.repeat(demo["actions"][:1], 60, axis=0)
    assert evaluate(_ReplayChunks(hold), env, episodes=1, seed=5)["success_once"] == 0.0
    # the flag is the env's own _check_success()
    inner = env.base_env._envs[0]
    out = inner.step(TensorDict({"action": torch.as_tensor(demo["actions"][0], dtype=torch.float32)}))
    assert bool(out["next", "success"]) == bool(inner.sim._check_success())
    env.close()


def test_worker_envs_step_and_reset_per_env():
    env = make_env("robosuite_lift", num_envs=2, render=False, max_episode_steps=6)
    try:
        check_env_specs(env, seed=0)
        first = seeded_reset(env, None, [3, 4])
        assert first["observation"].shape == (2, 2, 19)
        assert not torch.equal(first["observation"][0], first["observation"][1])
        td = env.rand_step(first)
        nxt = td["next"].clone()
        # reset env 1 only, to seed 3: it now shows env 0's initial scene; env 0 keeps its state
        again = seeded_reset(env, nxt, [None, 3])
        torch.testing.assert_close(again["observation"][1, -1], first["observation"][0, -1])
        torch.testing.assert_close(again["observation"][0], nxt["observation"][0])
    finally:
        env.close()


def test_missing_robosuite_names_the_install_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "robosuite", None)  # makes `import robosuite` fail
    with pytest.raises(ImportError, match=r"pip install 'l1flow-rl\[robosuite\]'"):
        sim.import_robosuite()


def test_task_without_state_keys_is_refused():
    task = dataclasses.replace(load_task_config("robosuite_lift"), state_keys=[])
    with pytest.raises(ValueError, match="state_keys is empty"):
        RobosuiteEnv(task, render=False)


def test_absolute_actions_are_world_frame_targets():
    task = load_task_config("robosuite_lift")
    env = sim.make_from_env_args(sim.env_args_for_task(task, cameras=[]))
    raw = env.reset()
    from scipy.spatial.transform import Rotation

    from l1flow_rl.experts.robosuite.scripted import canonical_rotvec

    target = raw["robot0_eef_pos"] + np.array([0.05, -0.04, 0.06])
    site = env.robots[0].eef_site_id["right"]
    home = Rotation.from_matrix(env.sim.data.site_xmat[site].reshape(3, 3))
    action = np.concatenate([target, canonical_rotvec(home), [-1.0]])
    for _ in range(40):
        raw, _ = sim.step(env, action)
    np.testing.assert_allclose(raw["robot0_eef_pos"], target, atol=0.01)


@pytest.mark.parametrize(
    ("task_name", "state_dim", "action_dim"),
    [("robosuite_square", 23, 7), ("robosuite_toolhang", 53, 7), ("robosuite_transport", 59, 14)],
)
def test_user_file_tasks_build_with_robomimic_widths(task_name, state_dim, action_dim):
    from l1flow_rl.data.formats.robomimic import expected_action_dim

    env = RobosuiteEnv(load_task_config(task_name, max_episode_steps=2), render=False)
    assert env.observation_spec["observation"].shape == (state_dim,)
    assert env.action_spec.shape == (action_dim,)
    # what the robomimic reader expects of a file recorded with these env_args
    assert expected_action_dim(env.env_args) == action_dim
    assert env.rollout(3)["next", "truncated"][-1]
    env.close()


def test_delta_control_is_bounded_and_passes_check_env_specs():
    task = dataclasses.replace(load_task_config("robosuite_lift", max_episode_steps=3), control="delta")
    env = RobosuiteEnv(task, render=False)
    arm = env.env_args["env_kwargs"]["controller_configs"]["body_parts"]["right"]
    assert arm["input_type"] == "delta"
    assert float(env.action_spec.space.low.min()) == -1.0 and float(env.action_spec.space.high.max()) == 1.0
    check_env_specs(env, seed=0)
    env.close()
