"""Scripts that make CPU worker envs without the ``if __name__ == "__main__":`` guard are told so,
instead of getting a ConnectionResetError from a worker that died while starting; a SIGTERM to the
whole process group leaves the workers to the main process; the main process keeps its torch
threads."""

from __future__ import annotations

import ast
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest
from l1flow_rl.envs.workers import _guarded, explain_worker_start_failure

SCRIPT_ERRORS = ("ConnectionResetError", "BrokenPipeError", "EOFError")


def run_script(tmp_path, source: str, timeout: int = 300) -> subprocess.CompletedProcess:
    script = tmp_path / "make_workers.py"
    script.write_text(textwrap.dedent(source))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.maniskill
def test_a_script_without_the_guard_is_told_to_add_it(tmp_path):
    pytest.importorskip("mani_skill")
    proc = run_script(
        tmp_path,
        """\
        from l1flow_rl.envs import make_env

        env = make_env("maniskill_pushcube", num_envs=2, max_episode_steps=5)
        env.rollout(3)
        """,
    )
    assert proc.returncode == 1
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("l1flow_rl.envs.workers.MainGuardError: ManiSkill on the CPU with num_envs=2")
    assert 'make_workers.py makes them at import time (line 3, outside `if __name__ == "__main__":`)' in last
    assert not any(name in proc.stderr for name in SCRIPT_ERRORS)
    assert "Process" not in proc.stderr  # refused before any worker started


@pytest.mark.slow
@pytest.mark.maniskill
def test_a_worker_that_dies_while_starting_is_explained(tmp_path):
    # With the up-front check switched off, the workers re-run the script and die: the parent's
    # broken pipe becomes an error that names the guard.
    pytest.importorskip("mani_skill")
    proc = run_script(
        tmp_path,
        """\
        from l1flow_rl.envs import workers

        workers.check_main_guard = lambda what: None
        from l1flow_rl.envs import make_env

        env = make_env("maniskill_pushcube", num_envs=2, max_episode_steps=5)
        """,
    )
    assert proc.returncode == 1
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith(
        "RuntimeError: ManiSkill on the CPU with num_envs=2 ('maniskill_pushcube'): a worker"
    )
    assert 'if __name__ == "__main__":' in last


GUARDED = """\
import sys
from x import make_env                              # 2


def main():
    return make_env(num_envs=2)                     # 6


if __name__ == "__main__" and len(sys.argv) < 5:
    env = make_env(                                 # 10
        num_envs=2,
    )
    main()                                          # 13
else:
    env = make_env(num_envs=2)                      # 15
if "__main__" == __name__:
    main()                                          # 17
if __name__ == "__mp_main__":
    main()                                          # 19
main()                                              # 20
"""


@pytest.mark.parametrize(
    ("line", "guarded"),
    [(2, False), (10, True), (11, True), (13, True), (15, False), (17, True), (19, False), (20, False)],
)
def test_guard_detection_reads_the_script(line, guarded):
    assert _guarded(ast.parse(GUARDED), line) is guarded


def test_a_broken_pipe_while_starting_names_the_guard():
    starting = r"making envs: a worker process exited while starting \(EOFError"
    with pytest.raises(RuntimeError, match=starting), explain_worker_start_failure("making envs"):
        raise EOFError
    with pytest.raises(ValueError, match="unrelated"), explain_worker_start_failure("making envs"):
        raise ValueError("unrelated")


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1)


@pytest.mark.parametrize(
    "task, kwargs",
    [
        pytest.param("pusht_image", {"backend": "parallel"}, id="pusht"),
        pytest.param("robosuite_lift", {"render": False}, marks=pytest.mark.robosuite, id="robosuite"),
    ],
)
def test_making_worker_envs_leaves_the_main_processs_signal_handlers_alone(task, kwargs):
    # the workers ignore the stop signals, but TorchRL also calls their factory in the main process
    # (for the specs): a parallel PushT env once left this process deaf to Ctrl-C and to SIGTERM
    pytest.importorskip({"pusht": "gym_pusht", "robosuite": "robosuite"}[task.split("_")[0]])
    from l1flow_rl.envs import make_env

    ours = {sig: signal.signal(sig, lambda *_: None) for sig in STOP_SIGNALS}  # as the run harness's
    mine = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    try:
        env = make_env(task, num_envs=2, **kwargs)
        try:
            env.reset()
            assert {sig: signal.getsignal(sig) for sig in STOP_SIGNALS} == mine
        finally:
            env.close()
    finally:
        for sig, handler in ours.items():
            signal.signal(sig, handler)


def test_worker_envs_leave_the_learners_torch_threads_as_the_user_set_them():
    # TorchRL's ParallelEnv drops the main process to threads - workers: on two cores with two
    # workers the update that follows each round of acting ran on one thread
    pytest.importorskip("gym_pusht")
    import torch
    from l1flow_rl.envs import make_env

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        env = make_env("pusht_image", num_envs=2, backend="parallel")
        try:
            env.reset()
            assert torch.get_num_threads() == 2
        finally:
            env.close()
    finally:
        torch.set_num_threads(before)


STOPPABLE = """\
import signal
import sys

from torchrl.envs.utils import step_mdp

from l1flow_rl.envs import make_env

stop = []


def main():
    env = make_env({task!r}, num_envs=2, max_episode_steps=1000, **{kwargs!r})
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))  # as the run harness: finish the step
    td = env.reset()
    print("ready", flush=True)
    while not stop:
        td = step_mdp(env.rand_step(td))
    env.rand_step(td)  # the workers still answer after the signal
    env.close()
    print("closed cleanly", flush=True)


if __name__ == "__main__":
    main()
"""


@pytest.mark.parametrize(
    "task, kwargs",
    [
        # ~25 s each; the ManiSkill case keeps the behaviour in the default run
        pytest.param(
            "robosuite_lift",
            {"render": False},
            marks=[pytest.mark.robosuite, pytest.mark.slow],
            id="robosuite",
        ),
        pytest.param("maniskill_pushcube", {}, marks=pytest.mark.maniskill, id="maniskill"),
    ],
)
def test_a_process_group_sigterm_leaves_the_workers_to_the_main_process(tmp_path, task, kwargs):
    # timeout, SLURM and docker stop signal the whole group: the workers and their forkserver must
    # outlive it, so that the main process can checkpoint and close them itself
    pytest.importorskip({"robosuite": "robosuite", "maniskill": "mani_skill"}[task.split("_")[0]])
    script = tmp_path / "stoppable.py"
    script.write_text(STOPPABLE.format(task=task, kwargs=kwargs))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, str(script)],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a job's
    )
    try:
        assert proc.stdout.readline().strip() == "ready", proc.stderr.read()[-3000:]
        time.sleep(1.0)  # mid-rollout
        os.killpg(proc.pid, signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, err[-3000:]
    assert "closed cleanly" in out and "Traceback" not in err, err[-3000:]


LEFT_OPEN = """\
from l1flow_rl.envs import make_env

KEEP = []


def main():
    env = make_env("maniskill_pushcube", num_envs=2, max_episode_steps=50)
    env.reset()
    KEEP.append(env)  # alive when the interpreter exits, never closed
    print("left open", flush=True)


if __name__ == "__main__":
    main()
"""


@pytest.mark.maniskill
def test_a_process_exits_with_an_env_it_never_closed(tmp_path):
    # multiprocessing's exit handler stops daemonic children with SIGTERM, which simulator workers
    # ignore: without our exit step the interpreter waited on them forever
    pytest.importorskip("mani_skill")
    script = tmp_path / "left_open.py"
    script.write_text(LEFT_OPEN)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0 and proc.stdout.strip() == "left open", proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr  # the workers are killed, not left to fail on a closed pipe


DROPPED = """\
import sys

from l1flow_rl import L1FlowActor, evaluate
from l1flow_rl.envs import make_env


def main(end):
    env = make_env("maniskill_pushcube", num_envs=2, max_episode_steps=8)  # never closed
    if end == "evaluate":  # the rollout helper, as docs/simulators.md shows it
        actor = L1FlowActor.for_state(obs_dim=35, action_dim=4, down_dims=(16, 32))
        evaluate(actor, env, episodes=2, seed=0)
    else:
        env.rand_step(env.reset())
    print("done", flush=True)
    if end == "sys.exit":
        sys.exit(3)


if __name__ == "__main__":
    main(sys.argv[1])
"""


@pytest.mark.maniskill
@pytest.mark.parametrize("end", ["return", "sys.exit", "evaluate"])
def test_a_script_that_drops_an_unclosed_env_exits_quietly(tmp_path, end):
    # the env, dropped when main() ends, is closed by gymnasium's __del__: SIGTERM (which the workers
    # ignore) and closed pipes, on which each worker printed an EOFError/BrokenPipeError traceback
    pytest.importorskip("mani_skill")
    script = tmp_path / "dropped.py"
    script.write_text(DROPPED)
    proc = subprocess.run(
        [sys.executable, str(script), end],
        cwd=tmp_path,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == (3 if end == "sys.exit" else 0), proc.stderr[-3000:]
    assert proc.stdout.strip().splitlines()[-1] == "done"
    assert "Traceback" not in proc.stderr and "Error" not in proc.stderr, proc.stderr[-3000:]


JOBS_THEN_CHILDREN = """\
import json
import multiprocessing
import sys

from l1flow_rl.commands.cli import main

if __name__ == "__main__":
    for args in json.loads(sys.argv[1]):
        rc = main(args)
        print("CHILDREN", rc, sorted(c.name for c in multiprocessing.active_children()), flush=True)
"""


@pytest.mark.maniskill
def test_train_and_eval_jobs_close_their_worker_envs(tmp_path):
    # TorchRL's envs report is_closed=True until started (a TransformedEnv always): the evaluator
    # closed only envs that said otherwise, so a train job's ManiSkill CPU workers (AsyncVectorEnv)
    # ran on until the interpreter exit, where they once hung it for 30 minutes
    pytest.importorskip("mani_skill")
    script = tmp_path / "jobs.py"
    script.write_text(JOBS_THEN_CHILDREN)
    small = ["eval.episodes=2", "eval.num_envs=2", "task.max_episode_steps=20"]
    run_dir = tmp_path / "run"
    data = f"data_dir={tmp_path / 'data'}"
    train = ["train", "task=maniskill_pushcube", "demos.num=3", "train.steps=10", data, f"run_dir={run_dir}"]
    ckpt = f"checkpoint={run_dir / 'checkpoints' / 'latest.pt'}"
    jobs = [[*train, *small], ["eval", ckpt, f"run_dir={tmp_path / 'eval'}", *small]]
    proc = subprocess.run(
        [sys.executable, str(script), json.dumps(jobs)],
        cwd=tmp_path,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    found = [line for line in proc.stdout.splitlines() if line.startswith("CHILDREN")]
    assert found == ["CHILDREN 0 []", "CHILDREN 0 []"], proc.stdout[-3000:]  # each job's rc, live children


@pytest.mark.parametrize(
    "task, kwargs",
    [
        pytest.param("pusht_state", {"backend": "parallel"}, id="pusht-parallel"),
        pytest.param("pusht_state", {"backend": "serial"}, id="pusht-serial"),
    ],
)
def test_an_env_closed_before_its_first_reset_closes_quietly(task, kwargs):
    # TorchRL counts batched envs as closed until their workers start, and raised on this close()
    pytest.importorskip("gym_pusht")
    from l1flow_rl.envs import make_env

    env = make_env(task, num_envs=2, **kwargs)
    env.close()
    env.close()  # nothing started, nothing to close: still quiet
    started = make_env(task, num_envs=2, **kwargs)
    assert started.rollout(2).shape == (2, 2)  # a started one runs and closes as before
    started.close()
    with pytest.raises(RuntimeError, match="closed environment"):
        started.close()  # closing a closed env is still the user's error, as in TorchRL
