"""make_env's dispatch and argument errors, without starting a simulator."""

import pytest
import torch
from l1flow_rl.envs import history_transforms, make_env, resolve_device
from l1flow_rl.envs.maniskill.env import ManiSkillEnv

from l1flow_rl.config import TaskConfig


def test_history_transforms_stack_each_entry_in_front_of_its_frame_dims():
    state = history_transforms({"observation": 1}, 3)
    assert [type(t).__name__ for t in state] == ["InitTracker", "UnsqueezeTransform", "CatFrames"]
    assert state[2].N == 3 and state[2].dim == -2
    rgb = history_transforms({("observation", "state"): 1, ("observation", "rgb"): 3}, 2)
    dims = {t.in_keys[0]: t.dim for t in rgb if type(t).__name__ == "CatFrames"}
    assert dims == {("observation", "state"): -2, ("observation", "rgb"): -4}
    with pytest.raises(ValueError, match="obs_horizon"):
        history_transforms({"observation": 1}, 0)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the no-CUDA error")
def test_the_gpu_path_says_when_there_is_no_cuda():
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(ValueError, match="device='cuda', but torch sees 0 CUDA device"):
        make_env("maniskill_pushcube", num_envs=256, device="cuda")


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="unknown task 'nope'"):
        make_env("nope")
    with pytest.raises(ValueError, match="num_envs must be >= 1"):
        make_env("maniskill_pushcube", num_envs=0)
    with pytest.raises(ValueError, match="cpu_backend must be one of \\('async', 'parallel'\\)"):
        make_env("maniskill_pushcube", num_envs=2, cpu_backend="threads")
    with pytest.raises(ValueError, match="unknown simulator 'nosuchsim'"):
        make_env(TaskConfig(name="x", simulator="nosuchsim"))
    with pytest.raises(TypeError, match=r"\['colour'\] are neither TaskConfig fields nor options"):
        make_env("maniskill_pushcube", colour="red")
    with pytest.raises(ValueError, match="one env per process"):
        ManiSkillEnv(TaskConfig(), num_envs=4)
    with pytest.raises(ValueError, match="obs_mode must be 'state' or 'rgb'"):
        ManiSkillEnv(TaskConfig(obs_mode="pointcloud"))
