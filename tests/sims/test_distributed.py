"""torchrun robustness: a failure on rank 0 ends every rank with that error, and rank-0-only work
longer than the process group's timeout does not trip it. Each case launches torchrun (gloo, 2 CPU
processes) in a fresh interpreter, as users launch DDP training."""

from __future__ import annotations

import json
import socket
import subprocess
import sys

import pytest


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _torchrun(args: list[str], cwd, timeout: float = 240) -> subprocess.CompletedProcess:
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node=2",
        "--master_addr=127.0.0.1",
        f"--master_port={_free_port()}",
        *args,
    ]
    env = {**__import__("os").environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=cwd, env=env)


_SCRIPT = """
import json, os, sys, time
from datetime import timedelta
import torch.distributed as dist
from l1flow_rl.workspace.distributed import (
    RankFailedError, init_distributed, raise_if_any_failed, run_on_every_rank, run_on_rank0,
)

# The ranks meet on torchrun's store first: the 3 s timeout below also bounds the group's own
# connection, which a rank that starts seconds after the other (a loaded CI machine) would miss.
store = dist.TCPStore(
    os.environ["MASTER_ADDR"], int(os.environ["MASTER_PORT"]), is_master=False,
    timeout=timedelta(seconds=120),
)
store.set(f"started/{{os.environ['RANK']}}", "1")
store.wait([f"started/{{r}}" for r in range(int(os.environ["WORLD_SIZE"]))])

# A default group whose timeout (3 s) is far shorter than rank 0's work below (6 s).
dist.init_process_group("gloo", timeout=timedelta(seconds=3))
rank, world = init_distributed()
out = {{"rank": rank}}

def slow():
    time.sleep(6)
    return "demos.h5"

out["slow"] = run_on_rank0(slow, "making demonstrations")

def fail_on_one_rank():
    if rank == 1:
        raise OSError("disk full on rank 1")
    return rank

try:
    run_on_every_rank(fail_on_one_rank, "loading the data")
except Exception as err:
    out["every_rank"] = f"{{type(err).__name__}}: {{str(err).splitlines()[0]}}"

def fail():
    raise FileNotFoundError("data.path='/nowhere/demos.h5' does not exist")

try:
    run_on_rank0(fail, "making demonstrations")
    out["rank0"] = "no error"
except Exception as err:
    out["rank0"] = f"{{type(err).__name__}}: {{str(err).splitlines()[0]}}"
with open({out!r} + f".{{rank}}", "w") as f:
    json.dump(out, f)
"""


def test_rank0_failure_and_long_rank0_work_under_torchrun(tmp_path):
    out = tmp_path / "result"
    script = tmp_path / "check.py"
    script.write_text(_SCRIPT.format(out=str(out)))
    proc = _torchrun([str(script)], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = [json.loads((tmp_path / f"result.{r}").read_text()) for r in (0, 1)]
    # 6 s of rank-0 work, waited for on the status group, outlived the default group's 3 s timeout.
    assert [r["slow"] for r in results] == ["demos.h5", "demos.h5"]
    # The rank that failed raised its own error; the other one raised it too, naming the rank.
    assert results[1]["every_rank"] == "OSError: disk full on rank 1"
    assert (
        results[0]["every_rank"]
        == "RankFailedError: rank 1 failed while loading the data: OSError: disk full on rank 1"
    )
    assert results[0]["rank0"] == "FileNotFoundError: data.path='/nowhere/demos.h5' does not exist"
    assert results[1]["rank0"] == (
        "RankFailedError: rank 0 failed while making demonstrations: "
        "FileNotFoundError: data.path='/nowhere/demos.h5' does not exist"
    )


def test_train_under_torchrun_ends_both_ranks_with_rank0s_error(tmp_path):
    """Rank 0 cannot make the demonstrations' folder (demonstrations are made there by rank 0 only):
    both processes stop with that error instead of rank 1 waiting for the dataset."""
    pytest.importorskip("mani_skill", reason="the task's expert is ManiSkill's motion planner")
    data_dir = tmp_path / "data"  # writable, so the config check passes it ...
    data_dir.mkdir()
    (data_dir / "maniskill").write_text("")  # ... but the expert's folder is blocked by a file
    proc = _torchrun(
        [
            "-m",
            "l1flow_rl.commands.cli",
            "train",
            f"data_dir={data_dir}",
            f"run_dir={tmp_path / 'run'}",
            "device=cpu",
        ],
        cwd=tmp_path,
    )
    assert proc.returncode != 0
    log = proc.stdout + proc.stderr
    assert "[rank0]: NotADirectoryError" in log, log[-3000:]
    assert (
        "[rank1]: l1flow_rl.workspace.distributed.RankFailedError: rank 0 failed while making or finding "
        "the demonstrations: NotADirectoryError" in log
    ), log[-3000:]
    assert "Connection closed by peer" not in log
