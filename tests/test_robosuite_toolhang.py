"""The scripted ToolHang expert on the real simulator: the frame goes into the stand and the tool
hangs on its hook in most episodes (0.82 over seeds 0-99, robosuite_experts.json), within the
task's 700 steps."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("robosuite")
pytestmark = pytest.mark.robosuite

from l1flow_rl.envs.robosuite import sim  # noqa: E402

from l1flow_rl.config import load_task_config  # noqa: E402
from l1flow_rl.experts.robosuite.demos import run_episode  # noqa: E402
from l1flow_rl.experts.robosuite.scripted import EXPERT_TASKS, ToolHangExpert  # noqa: E402


def test_toolhang_expert_succeeds_on_most_of_five_seeds():
    assert EXPERT_TASKS["ToolHang"] is ToolHangExpert
    task = load_task_config("robosuite_toolhang")
    env = sim.make_from_env_args(sim.env_args_for_task(task, cameras=[]))
    demos = [run_episode(env, task, seed) for seed in range(5)]
    done = [d for d in demos if d is not None]
    assert len(done) >= 4, f"{len(done)}/5 successes"
    for demo in done:
        # the stored last state is a success state: frame in the stand, tool hanging on its own
        sim.restore_state(env, demo["states"][-1])
        assert env._check_frame_assembled() and env._check_tool_on_frame()
        assert len(demo["actions"]) <= task.max_episode_steps
        # the hand turns through many orientations: the axis-angle actions must not jump by ~2 pi
        assert np.abs(np.diff(demo["actions"][:, 3:6], axis=0)).max() < 0.2
    # randomised: no two demonstrations share an action sequence
    assert len({tuple(np.round(d["actions"][5], 4)) for d in done}) == len(done)
