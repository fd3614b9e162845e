"""A core install (``pip install l1flow-rl``, no extras) imports the library, the data layer and the
losses, trains a loss and samples chunks, without h5py, zarr, tqdm, matplotlib, imageio or any
simulator.

The check runs in a fresh interpreter in which every distribution outside the core requirements
(and their requirements, read from the installed metadata) is hidden from the import system:
``import h5py`` fails and ``importlib.util.find_spec("h5py")`` is None, as on a machine where it was
never installed. (A second venv without extras would need the torch wheel installed again.)
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

HIDE_EXTRAS = textwrap.dedent(
    f"""
import importlib.abc
import importlib.metadata as md
import sys

sys.path.insert(0, {str(Path(__file__).parents[2])!r})
from core_install import core_distributions, extra_top_levels, norm as _norm

CORE = core_distributions()
HIDDEN = extra_top_levels(CORE)

class Hide(importlib.abc.MetaPathFinder):
    def __init__(self, inner):
        self.inner = inner

    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in HIDDEN:
            return None
        find = getattr(self.inner, "find_spec", None)
        return find(name, path, target) if find else None

    def find_distributions(self, context=md.DistributionFinder.Context()):
        find = getattr(self.inner, "find_distributions", None)
        if find is None:
            return iter(())
        return (d for d in find(context) if _norm(d.metadata["Name"] or "") in CORE or not d.metadata["Name"])

    def invalidate_caches(self):
        if hasattr(self.inner, "invalidate_caches"):
            self.inner.invalidate_caches()


sys.meta_path[:] = [Hide(f) for f in sys.meta_path]
"""
)

CHECK = textwrap.dedent(
    """
    import importlib.util
    for name in ("h5py", "zarr", "tqdm", "matplotlib", "imageio", "gymnasium", "mani_skill", "sapien",
                 "robosuite", "mujoco", "gym_pusht"):
        assert name in HIDDEN, name  # an extra, not a core requirement
        assert importlib.util.find_spec(name) is None, name

    import torch
    from tensordict import TensorDict

    import l1flow_rl
    from l1flow_rl import L1FlowActor, L1FlowLoss
    from l1flow_rl.data import load_episodes, make_chunk_buffer
    from l1flow_rl.data.episodes import assemble_episode
    from l1flow_rl.objectives import DiffusionLoss, FlowMatchingLoss, RegressionLoss  # noqa: F401

    torch.manual_seed(0)
    episodes = torch.cat([assemble_episode(e, torch.randn(20, 5), torch.rand(20, 2)) for e in range(3)])
    buffer = make_chunk_buffer(episodes, obs_horizon=2, pred_horizon=8, batch_size=4, seed=0)
    batch = buffer.sample()
    assert batch["observation"].shape == (4, 2, 5) and batch["action_chunk"].shape == (4, 8, 2)

    actor = L1FlowActor.for_state(obs_dim=5, action_dim=2, pred_horizon=8, action_steps=4, down_dims=(8, 16))
    loss = L1FlowLoss(actor)(batch)["loss_l1flow"]
    loss.backward()
    assert torch.isfinite(loss)
    chunk = actor(TensorDict({"observation": batch["observation"]}, [4]))["action_chunk"]
    assert chunk.shape == (4, 4, 2)

    try:
        load_episodes("demos.h5")
    except ImportError as err:  # the file reader says which extra to install
        assert "l1flow-rl[app]" in str(err), err
    else:
        raise AssertionError("an HDF5 file loaded without h5py")
    print("CORE OK")
    """
)


def _run_core(code: str, cwd) -> subprocess.CompletedProcess:
    """``code`` in a fresh interpreter that sees only the core requirements."""
    return subprocess.run(
        [sys.executable, "-c", HIDE_EXTRAS + code],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=cwd,
        env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"},
    )


def test_core_install_imports_and_trains_without_extras(tmp_path):
    (tmp_path / "demos.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(64))
    proc = _run_core(CHECK, tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "CORE OK" in proc.stdout


def test_core_install_composes_and_validates_the_cli_config(tmp_path):
    proc = _run_core(
        "from l1flow_rl.commands.cli import main\n"
        "raise SystemExit(main(['train', 'policy=ddpm', '--cfg', 'job']))",
        tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "sampler: ddpm" in proc.stdout
