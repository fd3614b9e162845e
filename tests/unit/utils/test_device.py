"""``device=`` is read by one function, whichever part of the library reads it."""

from __future__ import annotations

import pytest
import torch
from l1flow_rl.envs import resolve_device as from_envs

from l1flow_rl.utils.device import resolve_device
from l1flow_rl.workspace.distributed import resolve_device as from_jobs


def test_one_resolve_device_for_envs_and_jobs():
    assert from_envs is resolve_device and from_jobs is resolve_device


def test_names_resolve():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == expected


def test_a_bad_name_is_named():
    with pytest.raises(ValueError, match="device='gpu' is not a device name"):
        resolve_device("gpu")


def test_a_missing_cuda_device_is_refused_before_use():
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    with pytest.raises(ValueError, match=f"device='cuda:{count}', but torch sees {count} CUDA device"):
        resolve_device(f"cuda:{count}")
    if count == 0:
        with pytest.raises(ValueError, match="use device=cpu or device=auto"):
            resolve_device("cuda")
