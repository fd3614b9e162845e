"""Real ManiSkill demonstrations: generate PushCube demos, import them, check windows against the raw file."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import torch

pytest.importorskip("mani_skill")

from l1flow_rl.config import TaskConfig, load_task_config
from l1flow_rl.data import episodes_metadata, load_episodes, make_chunk_buffer
from l1flow_rl.experts import DemoGenerationError, ensure_demos
from l1flow_rl.experts.maniskill import demos as maniskill_demos

pytestmark = pytest.mark.maniskill


@pytest.fixture(scope="session")
def pushcube(tmp_path_factory):
    data_dir = tmp_path_factory.mktemp("demos")
    task = load_task_config("maniskill_pushcube")
    path = ensure_demos(task, 3, data_dir, progress=False)
    return path, data_dir, task


class _NoWorker:
    def __init__(self, *args, **kwargs):
        raise AssertionError("a worker was started although the cache had everything")


def test_generated_file_has_three_successful_delta_control_demos(pushcube):
    path, _, _ = pushcube
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["env_info"]["env_id"] == "PushCube-v1"
    assert [ep["control_mode"] for ep in meta["episodes"]] == ["pd_ee_delta_pos"] * 3
    assert all(ep["success"] for ep in meta["episodes"])
    with h5py.File(path) as f:
        assert sorted(f) == ["traj_0", "traj_1", "traj_2"]
        for name in f:
            steps = f[name]["actions"].shape[0]
            assert f[name]["actions"].shape == (steps, 4) and f[name]["obs"].shape[0] == steps + 1
            rewards = f[name]["rewards"][()]
            assert rewards.min() >= 0 and rewards.max() <= 1  # normalized_dense


def test_windows_match_the_raw_file_at_both_ends(pushcube):
    path, _, _ = pushcube
    eps = load_episodes(path, control_mode="pd_ee_delta_pos")
    with h5py.File(path) as f:
        raw = {int(k[5:]): (f[k]["obs"][()], f[k]["actions"][()], f[k]["rewards"][()]) for k in f}
    assert eps.shape == (sum(a.shape[0] for _, a, _ in raw.values()),)
    to, h = 2, 16
    batch = make_chunk_buffer(eps, obs_horizon=to, pred_horizon=h, batch_size=4096, seed=0).sample()
    covered = set(zip(batch["episode"].tolist(), batch["step"].tolist()))
    assert covered == {(e, t) for e, (_, a, _) in raw.items() for t in range(a.shape[0])}
    for i in range(batch.shape[0]):
        e, t = int(batch["episode"][i]), int(batch["step"][i])
        obs, actions, rewards = raw[e]
        n = actions.shape[0]
        obs_rows = np.clip(np.arange(t - to + 1, t + 1), 0, None)
        np.testing.assert_array_equal(batch["observation"][i].numpy(), obs[obs_rows])
        rows = np.arange(t - to + 1, t - to + 1 + h)
        expected = actions[np.clip(rows, 0, n - 1)].copy()
        expected[rows >= n, :3] = 0.0  # delta control: no arm motion past the end, gripper command kept
        np.testing.assert_array_equal(batch["action_chunk"][i].numpy(), expected)
        np.testing.assert_array_equal(batch["action_is_pad"][i].numpy(), (rows < 0) | (rows >= n))
        assert float(batch["next", "reward"][i]) == rewards[t]
    first = batch["step"] == 0
    assert torch.equal(batch["observation"][first, 0], batch["observation"][first, 1])
    assert batch["action_is_pad"][first, 0].all() and not batch["action_is_pad"][first, 1:].any()


def test_episodes_carry_rewards_terminations_and_final_observations(pushcube):
    path, _, _ = pushcube
    eps = load_episodes(path)
    meta = episodes_metadata(eps)
    assert (meta.format, meta.source, meta.env_id) == ("maniskill", str(path), "PushCube-v1")
    assert (meta.control_mode, meta.control) == ("pd_ee_delta_pos", "delta")
    assert meta.has_rewards and meta.has_final_observation
    with h5py.File(path) as f:
        for name in sorted(f):
            g, e = f[name], int(name[5:])
            ep = eps[eps["episode"] == e]
            n = g["actions"].shape[0]
            obs = g["obs"][()]
            assert ep.shape == (n,) and obs.shape[0] == n + 1
            np.testing.assert_array_equal(ep["next", "reward"][:, 0].numpy(), g["rewards"][()])
            np.testing.assert_array_equal(ep["observation"].numpy(), obs[:n])
            np.testing.assert_array_equal(
                ep["next", "observation"].numpy(), obs[1:]
            )  # the final one included
            assert ep["next", "done"][:, 0].tolist() == [False] * (n - 1) + [True]
            terminated = bool(g["terminated"][-1])
            assert bool(ep["next", "terminated"][-1]) == terminated and terminated  # the demos end in success
            assert not ep["next", "truncated"].any() and not ep["next", "terminated"][:-1].any()
    # the chunk return and the next observation at an episode's end, by hand from the raw file
    h, gamma = 4, 0.9
    batch = make_chunk_buffer(eps, batch_size=4096, seed=0, rl_horizon=h, gamma=gamma).sample()
    with h5py.File(path) as f:
        for i in range(batch.shape[0]):
            e, t = int(batch["episode"][i]), int(batch["step"][i])
            rewards, obs = f[f"traj_{e}/rewards"][()], f[f"traj_{e}/obs"][()]
            n = rewards.shape[0]
            if t < n - h - 1:
                continue  # the windows near the end: t+h < L, == L and > L
            expected = sum(gamma**k * float(rewards[t + k]) for k in range(min(h, n - t)))
            assert batch["next", "reward"][i].item() == pytest.approx(expected, rel=1e-5)
            rows = np.clip(np.arange(t + h - 1, t + h + 1), 0, n)
            np.testing.assert_array_equal(batch["next", "observation"][i].numpy(), obs[rows])
            assert bool(batch["next", "done"][i]) == (t + h >= n) == bool(batch["next", "terminated"][i])
            # every demo ends terminated (success): a chunk crossing that end stays valid, its
            # return summed to the end with no bootstrap
            assert bool(batch["chunk_valid"][i])


def test_cache_is_reused_and_generation_resumes(pushcube, monkeypatch):
    path, data_dir, task = pushcube
    with monkeypatch.context() as patch:
        patch.setattr(maniskill_demos, "_Worker", _NoWorker)
        # _NoWorker fails if any planning starts: both calls are served by the cache alone
        assert ensure_demos(task, 3, data_dir, progress=False) == path
        fewer = ensure_demos(task, 2, data_dir, progress=False)  # made from the cached batches
    with h5py.File(fewer) as small, h5py.File(path) as big:
        assert sorted(small) == ["traj_0", "traj_1"]
        np.testing.assert_array_equal(small["traj_1/actions"][()], big["traj_1/actions"][()])
    # leftovers of an interrupted run never count: a work directory and a batch without its attempts file
    root = maniskill_demos._task_root(task, data_dir)
    chain = maniskill_demos._planned_chain(root / "planned", 0)
    next_seed = chain[-1].last + 1
    (root / ".work" / "plan_000999").mkdir(parents=True)
    (root / ".work" / "plan_000999" / "plan.h5").write_bytes(b"half")
    (root / "planned" / f"seeds_{next_seed:06d}-{next_seed + 5:06d}.h5").write_bytes(b"half")
    generator = maniskill_demos._Generator(task, data_dir, attempt_timeout=120)
    usable = sum(ok for _, ok, _ in generator.outcomes(chain))
    more = ensure_demos(task, usable + 1, data_dir, progress=False)
    new_chain = maniskill_demos._planned_chain(root / "planned", 0)
    assert new_chain[: len(chain)] == chain  # the finished batches are kept
    assert new_chain[len(chain)].first == next_seed  # and only new seeds were planned
    assert not (root / ".work").exists()
    with h5py.File(more) as bigger, h5py.File(path) as three:
        assert len(bigger) == usable + 1
        for k in three:
            np.testing.assert_array_equal(bigger[k]["actions"][()], three[k]["actions"][()])


def test_cli_prints_the_dataset_path(pushcube, capsys):
    from l1flow_rl.commands.cli import main

    path, data_dir, _ = pushcube
    assert main(["demos", "task=maniskill_pushcube", "demos.num=3", f"data_dir={data_dir}"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == str(path)


def test_a_planner_that_always_fails_ends_with_a_clear_error(tmp_path):
    # DrawTriangle's solution is broken in mani-skill 3.0.1: every seed fails
    task = TaskConfig(name="drawtriangle", env_id="DrawTriangle-v1", reward_mode="sparse")
    with pytest.raises(
        DemoGenerationError, match=r"DrawTriangle-v1: 3 seeds in a row failed \(seeds 0\.\.2"
    ) as err:
        ensure_demos(task, 2, tmp_path, max_consecutive_failures=3, progress=False)
    assert "0/2 demonstrations made" in str(err.value) and "TypeError" in str(err.value)


def test_non_maniskill_task_is_refused(tmp_path):
    with pytest.raises(DemoGenerationError, match="no expert makes demonstrations for simulator 'nosuchsim'"):
        ensure_demos(TaskConfig(name="x", simulator="nosuchsim", env_id="X"), 1, tmp_path)


@pytest.mark.slow
def test_rgb_demos_import_as_state_plus_image(tmp_path):
    task = load_task_config("maniskill_pushcube", obs_mode="rgb")
    eps = load_episodes(ensure_demos(task, 2, tmp_path, progress=False))
    assert eps["observation", "rgb"].dtype == torch.uint8 and eps["observation", "rgb"].shape[1:] == (
        3,
        128,
        128,
    )
    batch = make_chunk_buffer(eps, batch_size=8).sample()
    assert batch["observation", "rgb"].shape == (8, 2, 3, 128, 128)
    assert batch["observation", "state"].shape == (8, 2, eps["observation", "state"].shape[-1])


@pytest.mark.parametrize(
    ("seed", "deepest"),
    [
        (0, True),  # cube at x = 0.0: the full 5 cm push is direct
        (19, False),  # cube at x = 0.094: a 5 cm push plans 800 steps through a wrist reconfiguration
        (65, False),  # cube at x = 0.095: no screw path for 2-5 cm
    ],
)
def test_pushcube_solution_pushes_as_deep_as_a_direct_push_reaches(seed, deepest):
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  (registers the tasks)

    from l1flow_rl.experts.maniskill.solutions import MAX_DIRECT_PUSH_STEPS, PUSH_FURTHER, solution_for

    env = gym.make("PushCube-v1", obs_mode="none", control_mode="pd_joint_pos", sim_backend="cpu")
    try:
        result = solution_for("PushCube-v1")(env, seed=seed)
        assert result != -1, f"seed {seed}: no plan"
        assert bool(result[-1]["success"].item())
        base = env.unwrapped
        # the approach takes at most 40 steps, the push at most MAX_DIRECT_PUSH_STEPS
        assert int(base.elapsed_steps.max()) <= 40 + MAX_DIRECT_PUSH_STEPS
        cube_to_goal = float(base.goal_region.pose.p[0, 0] - base.obj.pose.p[0, 0])
    finally:
        env.close()
    # the hand stops (0.12 - depth) short of the goal's centre with the cube 4 cm ahead of it
    full_depth = 0.12 - PUSH_FURTHER[0] - 0.04
    if deepest:
        assert cube_to_goal == pytest.approx(full_depth, abs=0.01)
    else:
        assert full_depth + 0.005 < cube_to_goal < 0.1
