"""A machine without a usable Vulkan device gets told what to install, not a bare driver error."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytest.importorskip("mani_skill", reason="needs ManiSkill: pip install 'l1flow-rl[maniskill]'")

pytestmark = pytest.mark.maniskill


def test_missing_vulkan_names_the_packages_to_install():
    script = (
        "import torch\n"
        "from l1flow_rl.config import load_task_config\n"
        "from l1flow_rl.envs.maniskill.env import make_gym_env\n"
        "make_gym_env(load_task_config('maniskill_pushcube'), 1, torch.device('cpu'))\n"
    )
    # Point the Vulkan loader at no driver at all: what a machine without lavapipe looks like.
    env = {
        **os.environ,
        "VK_ICD_FILENAMES": "/nonexistent/icd.json",
        "VK_DRIVER_FILES": "/nonexistent/icd.json",
    }
    proc = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode != 0
    assert "mesa-vulkan-drivers" in proc.stderr
    assert "libvulkan1" in proc.stderr
