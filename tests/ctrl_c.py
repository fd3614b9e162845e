"""A terminal's Ctrl-C to ``l1flow-rl demos`` once its progress bar is up (the worker pool has started),
and what must follow: exit 130 in seconds with the CLI's one message, no traceback (the workers leave
SIGINT to the main process) and no worker left running."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import pytest


def _start_like_a_launcher() -> None:
    # a terminal's process starts with SIGINT at its default; a test run launched in the background
    # (``pytest &``) would hand down an ignored SIGINT, which the command rightly keeps ignoring.
    # SIGTERM comes ignored, as some launchers (and once a full test run here) hand it down: the
    # workers must still end when the pool is shut down, or it waits for them forever
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def ctrl_c_after_the_progress_bar(overrides: list[str], unit: str, settle_s: float = 3.0) -> str:
    """Run ``l1flow-rl demos OVERRIDES``, send SIGINT to its process group ``settle_s`` after the bar
    (whose text holds ``unit``) appears, check the outcome above, and return its stderr."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "l1flow_rl.commands.cli", "demos", *overrides],
        stdout=subprocess.DEVNULL,  # never read: a pipe could fill and block the command
        stderr=subprocess.PIPE,
        start_new_session=True,
        preexec_fn=_start_like_a_launcher,
    )
    # stderr is drained all along (a full pipe would block the command's writes: a hang of the test's
    # making), and shown if the command outlives the guard
    chunks: list[str] = []
    fd = proc.stderr.fileno()  # raw reads: the progress bar redraws with \r, not newlines

    def read_all() -> None:
        for chunk in iter(lambda: os.read(fd, 4096), b""):
            chunks.append(chunk.decode(errors="replace"))

    drain = threading.Thread(target=read_all, daemon=True)
    drain.start()
    try:
        deadline = time.monotonic() + 120
        while not any(unit in c for c in chunks):  # the progress bar is up: the pool has started
            assert proc.poll() is None, "".join(chunks)
            assert time.monotonic() < deadline, "no progress bar within 120 s"
            time.sleep(0.1)
        time.sleep(settle_s)  # workers are mid-episode
        os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
        try:
            rc = proc.wait(timeout=90)  # a hang guard; a loaded machine took over 30 s
        except subprocess.TimeoutExpired:
            pytest.fail(f"still running 90 s after Ctrl-C; its stderr:\n{''.join(chunks)[-3000:]}")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    drain.join(timeout=10)
    text = "".join(chunks)
    assert rc == 130, text[-2000:]
    assert "interrupted" in text
    assert "Traceback" not in text, f"the workers were interrupted mid-episode too:\n{text[-2000:]}"
    time.sleep(1)
    ps = subprocess.run(["ps", "-o", "pid=,stat=,args=", "-s", str(proc.pid)], capture_output=True, text=True)
    # zombies are not running; they wait for the container's init to reap them
    alive = [line for line in ps.stdout.splitlines() if line.split()[1][0] != "Z"]
    assert not alive, f"workers outlived the interrupted command: {alive}"
    return text
