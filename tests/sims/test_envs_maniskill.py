"""ManiSkill PushCube through make_env on the real simulator (physx_cpu): specs, history stacking,
time limit, seeds, partial resets, and the chunk executor (MultiStepActorWrapper) on top."""

import pytest
import torch

pytest.importorskip("mani_skill")

from l1flow_rl.envs import make_env
from l1flow_rl.envs.contract import check_env_contract
from l1flow_rl.envs.maniskill.async_env import ManiSkillAsyncEnv
from l1flow_rl.envs.per_env import render_frames, seeded_reset, sim_error_messages
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import ParallelEnv
from torchrl.envs.utils import check_env_specs, step_mdp
from torchrl.modules import MultiStepActorWrapper

pytestmark = pytest.mark.maniskill

STEPS = 6  # max_episode_steps in these tests
STATE_DIM, RGB_STATE_DIM, IMAGE = 35, 25, 64


@pytest.fixture(scope="module")
def state1():
    env = make_env("maniskill_pushcube", max_episode_steps=STEPS)
    yield env
    env.close()


@pytest.fixture(scope="module")
def state2():
    env = make_env("maniskill_pushcube", num_envs=2, max_episode_steps=STEPS)
    yield env
    env.close()


@pytest.mark.parametrize("num_envs", [1, 2])
def test_state_specs_pass_check_env_specs(num_envs, state1, state2):
    env = state1 if num_envs == 1 else state2
    check_env_specs(env)
    td = env.reset()
    assert td["observation"].shape == (num_envs, 2, STATE_DIM)
    assert td["is_init"].all()
    assert env.action_spec.shape == (num_envs, 4)
    assert set(env.full_done_spec.keys()) == {"done", "terminated", "truncated"}


# two envs (~20 s) are slow; one env keeps RGB specs checked by default
@pytest.mark.parametrize("num_envs", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_rgb_specs_pass_check_env_specs(num_envs):
    env = make_env(
        "maniskill_pushcube", num_envs=num_envs, obs_mode="rgb", image_size=IMAGE, max_episode_steps=4
    )
    try:
        check_env_specs(env)
        obs = env.rollout(3)["next", "observation"]
        assert obs["state"].shape == (num_envs, 3, 2, RGB_STATE_DIM) and obs["state"].dtype == torch.float32
        assert obs["rgb"].shape == (num_envs, 3, 2, 3, IMAGE, IMAGE) and obs["rgb"].dtype == torch.uint8
        assert obs["rgb"].float().std() > 0  # a real camera image, not a blank buffer
        # history: the newer frame of step t is the older frame of step t + 1
        assert torch.equal(obs["rgb"][:, 1:, 0], obs["rgb"][:, :-1, 1])
    finally:
        env.close()


def test_history_pads_at_reset_and_shifts_each_step(state1):
    td = state1.reset(seed=[0])
    obs0 = td["observation"]
    assert torch.equal(obs0[:, 0], obs0[:, 1])  # padded with copies of the first observation
    td["action"] = torch.ones(1, 4)
    nxt = state1.step(td)["next", "observation"]
    assert torch.equal(nxt[:, 0], obs0[:, 1]) and not torch.equal(nxt[:, 1], obs0[:, 1])


def test_time_limit_and_seeded_resets(state1):
    rollout = state1.rollout(STEPS + 5, auto_reset=True, break_when_any_done=True)
    assert rollout.batch_size == (1, STEPS)  # truncated at max_episode_steps, never terminated
    assert rollout["next", "truncated"][0, -1].item() and not rollout["next", "truncated"][0, :-1].any()
    assert not rollout["next", "terminated"].any()
    first = state1.reset(seed=[7])["observation"].clone()
    assert torch.equal(state1.reset(seed=[7])["observation"], first)
    assert not torch.equal(state1.reset(seed=[8])["observation"], first)


def test_partial_reset_resets_only_the_masked_worker(state2):
    fresh = seeded_reset(state2, None, [11, 12])["observation"].clone()
    td = seeded_reset(state2, None, [5, 6])
    for _ in range(3):
        td = step_mdp(state2.rand_step(td))
    before = td["observation"].clone()
    td = seeded_reset(state2, td, [11, None])
    assert td["is_init"].squeeze(-1).tolist() == [True, False]
    assert torch.equal(td["observation"][0], fresh[0])  # env 0 starts seed 11's episode
    assert torch.equal(td["observation"][1], before[1])  # env 1 goes on where it was
    with pytest.raises(ValueError, match="got 1 seeds for 2"):
        seeded_reset(state2, td, [1])


def test_two_workers_run_on_the_async_backend_and_render(state2):
    assert isinstance(state2.base_env, ManiSkillAsyncEnv)
    seeded_reset(state2, None, [1, 2])
    frames = render_frames(state2)
    assert frames.shape[0] == 2 and frames.shape[-1] == 3 and frames.dtype == torch.uint8
    assert not torch.equal(frames[0], frames[1])  # each worker renders its own scene
    assert sim_error_messages(state2) == [None, None]


def test_parallel_backend_starts_the_same_seeded_episodes(state2):
    parallel = make_env("maniskill_pushcube", num_envs=2, max_episode_steps=STEPS, cpu_backend="parallel")
    try:
        assert isinstance(parallel.base_env, ParallelEnv)
        check_env_specs(parallel)
        got = seeded_reset(parallel, None, [3, 4])["observation"]
        assert torch.equal(got, seeded_reset(state2, None, [3, 4])["observation"])
    finally:
        parallel.close()


class ChunkCounter(TensorDictModuleBase):
    """A chunk actor that records its calls; action k of call c is (k / 10, c / 100, 0, 0)."""

    def __init__(self, chunk: int) -> None:
        super().__init__()
        self.in_keys, self.out_keys = ["observation"], ["action_chunk"]
        self.chunk, self.calls = chunk, []

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        call = len(self.calls)
        self.calls.append(td.batch_size[0])
        out = torch.zeros(*td.batch_size, self.chunk, 4)
        out[..., 0] = torch.arange(self.chunk) / 10
        out[..., 1] = call / 100
        return td.set("action_chunk", out)


def test_chunk_executor_replans_every_action_steps_and_after_resets(state2):
    k = 4
    actor = ChunkCounter(k)
    executor = MultiStepActorWrapper(actor, n_steps=k, init_key="is_init")
    rollout = state2.rollout(2 * STEPS, executor, break_when_any_done=False)
    # episodes of 6 steps, chunks of 4: re-plan at steps 0 and 4, then again at the reset (step 6)
    assert actor.calls == [2, 2, 2, 2]
    index_in_chunk = (rollout["action"][..., 0] * 10).round().long()
    call = (rollout["action"][..., 1] * 100).round().long()
    assert index_in_chunk.tolist() == [[0, 1, 2, 3, 0, 1] * 2] * 2
    assert call.tolist() == [[0, 0, 0, 0, 1, 1, 2, 2, 2, 2, 3, 3]] * 2
    assert rollout["next", "done"].squeeze(-1)[:, [STEPS - 1, 2 * STEPS - 1]].all()

    # a reset of one env mid-chunk re-plans that env alone; the other keeps executing its chunk
    actor.calls.clear()
    td = executor(seeded_reset(state2, None, [1, 2]))
    for _ in range(2):
        td = executor(step_mdp(state2.step(td)))
    td = executor(seeded_reset(state2, step_mdp(state2.step(td)), [3, None]))
    assert actor.calls == [2, 1]
    assert (td["action"][:, 0] * 10).round().tolist() == [0, 3]


@pytest.mark.parametrize("num_envs", [1, 2])
def test_state_envs_honour_the_simulator_contract(num_envs, state1, state2):
    check_env_contract(state1 if num_envs == 1 else state2)


def test_physx_cuda_without_its_gpu_library_names_the_file_and_the_url(tmp_path, monkeypatch):
    # Offline, SAPIEN's first-use download of libPhysXGpu_64.so fails deep inside gym.make with a bare
    # connection error; the adapter names the file and where it comes from. SAPIEN's own enable_gpu
    # runs here, with the network cut at requests.get.
    pytest.importorskip("mani_skill")
    import requests
    from l1flow_rl.envs.maniskill.env import _check_physx_gpu_library, physx_gpu_library

    monkeypatch.setenv("HOME", str(tmp_path))

    def offline(url, *args, **kwargs):
        raise requests.ConnectionError(f"no route to {url}")

    monkeypatch.setattr(requests, "get", offline)
    path, url = physx_gpu_library()
    assert path.parent.parent == tmp_path / ".sapien" / "physx" and path.name == "libPhysXGpu_64.so"
    with pytest.raises(RuntimeError) as err:
        _check_physx_gpu_library()
    message = str(err.value)
    assert str(path) in message and url in message and "ConnectionError" in message
