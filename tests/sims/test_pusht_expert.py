"""The PushT expert on the real simulator: it solves the task going around either side, its zarr
store has Diffusion Policy's layout, and a stored episode replays to the same coverage."""

from __future__ import annotations

import numpy as np
import pytest
from ctrl_c import ctrl_c_after_the_progress_bar
from l1flow_rl.envs.pusht import pusht_reader_options
from l1flow_rl.envs.pusht.geometry import block_keypoints, reset_state_for

from l1flow_rl.config import load_task_config
from l1flow_rl.data import EpisodeDataError, load_episodes
from l1flow_rl.experts import ensure_demos
from l1flow_rl.experts.pusht.demos import SIDE_CODES, run_episodes

pytest.importorskip("gym_pusht", reason="needs gym-pusht: pip install 'l1flow-rl[pusht]'")
zarr = pytest.importorskip("zarr")
pytestmark = pytest.mark.pusht

#: five seeds whose episodes choose a side freely, both ways (benchmarks/results/pusht_expert.json:
#: 3 and 9 go right, 14, 17 and 28 left; all short)
SEEDS = [3, 9, 14, 17, 28]


@pytest.fixture(scope="module")
def demos():
    return {seed: demo for seed, demo, _ in run_episodes(SEEDS, workers=1, progress=False)}


def test_expert_succeeds_on_most_seeds_on_both_sides(demos):
    assert sum(d is not None and d.success for d in demos.values()) >= 4
    sides = {d.side for d in demos.values() if d is not None and d.success}
    assert {"left", "right"} <= sides, sides
    for d in demos.values():
        assert d.score == pytest.approx(float(d.arrays["reward"].max()))
        assert d.steps <= 300


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    data_dir = tmp_path_factory.mktemp("pusht_demos")
    return ensure_demos(load_task_config("pusht"), 2, data_dir, seed=14, workers=1, progress=False)


def test_zarr_store_has_diffusion_policys_layout(store):
    root = zarr.open_group(str(store), mode="r")
    ends = root["meta/episode_ends"][:]
    n = int(ends[-1])
    assert ends.dtype == np.int64 and len(ends) == 2
    assert root["data/action"].shape == (n, 2) and root["data/action"].dtype == np.float32
    assert root["data/state"].shape == (n, 5) and root["data/state"].dtype == np.float32
    assert root["data/keypoint"].shape == (n, 9, 2)
    assert root["data/n_contacts"].shape == (n, 1)
    assert root["data/reward"].shape == (n,)
    np.testing.assert_allclose(root["data/keypoint"][:], block_keypoints(root["data/state"][:]), atol=1e-3)
    assert set(root["meta/side"][:]) <= set(SIDE_CODES.values())
    assert root["meta/terminated"][:].all()
    # again: the cache is reused, not regenerated
    before = store.stat().st_mtime_ns
    assert ensure_demos(load_task_config("pusht"), 2, store.parent.parent, seed=14) == store
    assert store.stat().st_mtime_ns == before


def test_episodes_read_back_as_the_task_observes_them(store):
    root = zarr.open_group(str(store), mode="r")
    eps = load_episodes(store, **pusht_reader_options(load_task_config("pusht")))
    state = root["data/state"][:]
    want = np.concatenate([root["data/keypoint"][:].reshape(-1, 18), state[:, :2]], axis=1)
    np.testing.assert_allclose(eps["observation"].numpy(), want)
    np.testing.assert_allclose(eps["next", "reward"].numpy()[:, 0], root["data/reward"][:])
    assert eps["next", "terminated"].sum() == 2 and eps["next", "done"].sum() == 2
    state_eps = load_episodes(store, **pusht_reader_options(load_task_config("pusht_state")))
    np.testing.assert_allclose(state_eps["observation"].numpy(), state)


def test_replaying_stored_actions_from_the_stored_first_state_reproduces_coverage(store):
    import gymnasium as gym

    root = zarr.open_group(str(store), mode="r")
    ends = root["meta/episode_ends"][:]
    starts = np.concatenate([[0], ends[:-1]])
    env = gym.make("gym_pusht/PushT-v0", obs_type="state", disable_env_checker=True)
    for start, end in zip(starts, ends):
        obs, _ = env.reset(
            options={"reset_to_state": reset_state_for(root["data/state"][start].astype(float))}
        )
        np.testing.assert_array_equal(obs.astype(np.float32), root["data/state"][start])
        rewards, coverage = [], 0.0
        for action in root["data/action"][start:end]:
            obs, reward, _, _, info = env.step(action.astype(np.float64))
            rewards.append(reward)
            coverage = max(coverage, info["coverage"])
        np.testing.assert_array_equal(np.float32(rewards), root["data/reward"][start:end])
        assert coverage > 0.95


def _copy_store(src, dst):
    import shutil

    shutil.copytree(src, dst)
    return zarr.open_group(str(dst), mode="r+")


def test_malformed_zarr_gets_a_clear_error(store, tmp_path):
    import shutil

    options = pusht_reader_options(load_task_config("pusht"))
    missing = tmp_path / "missing.zarr"
    _copy_store(store, missing)
    shutil.rmtree(missing / "meta" / "episode_ends")
    with pytest.raises(EpisodeDataError, match="meta/episode_ends"):
        load_episodes(missing, **options)

    short = tmp_path / "short.zarr"
    root = _copy_store(store, short)
    ends = root["meta/episode_ends"][:]
    root["meta/episode_ends"][-1] = ends[-1] + 5  # more rows claimed than the arrays hold
    with pytest.raises(EpisodeDataError, match=r"rows but meta/episode_ends ends at"):
        load_episodes(short, **options)

    nan = tmp_path / "nan.zarr"
    root = _copy_store(store, nan)
    row = int(ends[0]) + 3  # episode 1, step 3
    values = root["data/action"][:]
    values[row, 1] = np.nan
    root["data/action"][:] = values
    with pytest.raises(
        EpisodeDataError, match=r"episode 1: key 'data/action': contains NaN or Inf \(first at step 3\)"
    ):
        load_episodes(nan, **options)


def test_image_demo_matches_what_the_image_env_observes(tmp_path):
    """Image demonstrations (pusht_image): data/img uint8 [T, 96, 96, 3], read back as the env's
    ``rgb`` [3, 96, 96] next to the agent position; the first frame equals the env's own frame after
    a reset to the stored first state."""
    import torch
    from l1flow_rl.envs.pusht.env import PushTEnv

    task = load_task_config("pusht_image")
    path = ensure_demos(task, 1, tmp_path, seed=14, workers=1, progress=False)
    root = zarr.open_group(str(path), mode="r")
    n = int(root["meta/episode_ends"][-1])
    assert root["data/img"].shape == (n, 96, 96, 3) and root["data/img"].dtype == np.uint8
    eps = load_episodes(path, **pusht_reader_options(task))
    assert eps["observation", "rgb"].shape == (n, 3, 96, 96)
    np.testing.assert_allclose(eps["observation", "state"].numpy(), root["data/state"][:, :2])
    env = PushTEnv(task)
    first = env.reset(options={"reset_to_state": reset_state_for(root["data/state"][0].astype(float))})
    assert torch.equal(first["observation", "rgb"], eps["observation", "rgb"][0])


def test_a_diffusion_policy_file_reads_with_the_pusht_tasks(store, tmp_path):
    """A file as Diffusion Policy ships it (float32 images in [0, 255], no rewards, no extras)
    reads with each PushT task's options: keypoints + agent_pos (20-D), state, image + agent_pos."""
    root = zarr.open_group(str(store), mode="r")
    n = int(root["meta/episode_ends"][-1])
    dp = zarr.open_group(str(tmp_path / "pusht_cchi_like.zarr"), mode="w", zarr_format=2)
    arrays = {
        "action": root["data/action"][:],
        "state": root["data/state"][:],
        "keypoint": root["data/keypoint"][:],
        "n_contacts": root["data/n_contacts"][:],
        "img": np.random.default_rng(0).integers(0, 256, (n, 96, 96, 3)).astype(np.float32),
    }
    for key, value in arrays.items():
        dp.create_array(f"data/{key}", shape=value.shape, dtype=value.dtype)[:] = value
    ends = root["meta/episode_ends"][:]
    dp.create_array("meta/episode_ends", shape=ends.shape, dtype=ends.dtype)[:] = ends
    path = tmp_path / "pusht_cchi_like.zarr"
    low = load_episodes(path, **pusht_reader_options(load_task_config("pusht")))
    assert low["observation"].shape == (n, 20)
    assert not low["next", "reward"].any()  # no rewards in Diffusion Policy's files
    image = load_episodes(path, **pusht_reader_options(load_task_config("pusht_image")))
    np.testing.assert_array_equal(image["observation", "rgb"][0].permute(1, 2, 0).numpy(), arrays["img"][0])
    assert image["observation", "state"].shape == (n, 2)


def test_ctrl_c_stops_the_demo_workers_promptly(tmp_path):
    """SIGINT reaches the whole process group; the spawned workers ignore it and the parent ends the
    pool, so ``l1flow-rl demos`` exits with 130 in seconds, quietly (no traceback from each worker),
    and leaves no worker running."""
    ctrl_c_after_the_progress_bar(["task=pusht", "demos.num=50", f"data_dir={tmp_path}"], "episode")
    assert not list((tmp_path / "pusht").glob("*.zarr")), "an interrupted run must not leave a demo store"
