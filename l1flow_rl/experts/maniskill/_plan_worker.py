"""Subprocess entry for one batch of ManiSkill demonstrations: plan, then replay into the target modes.

    python -m l1flow_rl.experts.maniskill._plan_worker --env-id PushCube-v1 --work-dir TMP \
        --first-seed 0 --num-seeds 20 --obs-mode state --control-mode pd_ee_delta_pos

Stage 1 (with ``--num-seeds``) runs the motion-planning solution (ManiSkill's, or ours where
:mod:`l1flow_rl.experts.maniskill.solutions` replaces it) on each seed and writes the
successes to ``TMP/plan.h5`` + ``plan.json`` (ManiSkill's format, ``pd_joint_pos``); one
``ATTEMPT_MARK {json}`` line per seed goes to stdout for the parent's progress bar and failure count.
The official runner (``mani_skill.examples.motionplanning.panda.run``) always starts at seed 0 and,
with ``--only-count-success``, never returns for a task whose planner always fails; this worker takes
a seed range and a per-attempt time limit instead, so every batch covers new seeds and ends.

Stage 2 (with ``--obs-mode``) replays ``TMP/plan.h5`` through ManiSkill's own replay tool
(``mani_skill.trajectory.replay_trajectory``, called in-process to spare a second interpreter start)
into ``TMP/plan.<obs_mode>.<control_mode>.physx_cpu.h5``. Without ``--num-seeds`` the parent has put
an already planned ``plan.h5`` there, and only the replay runs.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path

from l1flow_rl.experts.maniskill.solutions import solution_for

ATTEMPT_MARK = "L1FLOW_PLAN_ATTEMPT"
READY_MARK = "L1FLOW_PLAN_READY"  # the env is up: a crash after this is the planner's, on a seed
NO_SOLUTION_EXIT = 3


class _AttemptTimeout(Exception):
    pass


def _on_alarm(signum, frame):  # pragma: no cover - only fires on a stuck planner
    raise _AttemptTimeout


def _plan(env_id: str, work_dir: Path, first_seed: int, num_seeds: int, attempt_timeout: int) -> int:
    # optional dependency: the simulator and its planner (maniskill extra)
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  (registers the tasks)
    from mani_skill.examples.motionplanning.panda.run import MP_SOLUTIONS
    from mani_skill.utils.wrappers.record import RecordEpisode

    solve = solution_for(env_id)
    if solve is None:
        print(
            f"no motion-planning solution for {env_id}; ManiSkill has {sorted(MP_SOLUTIONS)}", file=sys.stderr
        )
        return NO_SOLUTION_EXIT
    # The solutions plan in joint space; pd_joint_pos is what they record (the replay converts it).
    env = gym.make(
        env_id, obs_mode="none", control_mode="pd_joint_pos", render_mode="rgb_array", sim_backend="cpu"
    )
    env = RecordEpisode(
        env,
        output_dir=str(work_dir),
        trajectory_name="plan",
        save_video=False,
        source_type="motionplanning",
        source_desc="ManiSkill's motion planning solution, run by l1flow_rl.experts.maniskill._plan_worker",
        record_reward=False,
        save_on_reset=False,
    )
    signal.signal(signal.SIGALRM, _on_alarm)
    print(READY_MARK, flush=True)
    for seed in range(first_seed, first_seed + num_seeds):
        start = time.perf_counter()
        error = None
        success = False
        signal.alarm(attempt_timeout)
        try:
            result = solve(env, seed=seed, debug=False, vis=False)
            if isinstance(result, int) and result == -1:
                error = "the planner found no path"
            else:
                success = bool(result[-1]["success"].item())
                error = None if success else "the plan ran but the task was not solved"
        except _AttemptTimeout:
            error = f"the attempt took longer than {attempt_timeout} s"
        except Exception as err:  # a solution raising (unreachable grasp, API mismatch) is a failed attempt
            error = f"{type(err).__name__}: {err}"
        finally:
            signal.alarm(0)
        env.flush_trajectory(save=success)
        record = {
            "seed": seed,
            "success": success,
            "seconds": round(time.perf_counter() - start, 3),
            "error": error,
        }
        print(f"{ATTEMPT_MARK} {json.dumps(record)}", flush=True)
    env.close()
    return 0


def _replay(work_dir: Path, obs_mode: str, control_mode: str, reward_mode: str) -> None:
    # optional dependency: the simulator (maniskill extra)
    from mani_skill.trajectory import replay_trajectory

    argv = [
        "--traj-path", str(work_dir / "plan.h5"),
        "-b", "physx_cpu",
        "-o", obs_mode,
        "-c", control_mode,
        "--save-traj",
        "--record-rewards",
        "--reward-mode", reward_mode,
    ]  # fmt: skip
    replay_trajectory.main(replay_trajectory.parse_args(argv))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--env-id", required=True)
    parser.add_argument("--work-dir", required=True, type=Path)
    parser.add_argument("--first-seed", type=int)
    parser.add_argument("--num-seeds", type=int)
    parser.add_argument("--attempt-timeout", type=int, default=120)
    parser.add_argument("--obs-mode")
    parser.add_argument("--control-mode", default="pd_ee_delta_pos")
    parser.add_argument("--reward-mode", default="normalized_dense")
    args = parser.parse_args(argv)
    if args.num_seeds is not None:
        code = _plan(args.env_id, args.work_dir, args.first_seed, args.num_seeds, args.attempt_timeout)
        if code:
            return code
    if args.obs_mode is not None:
        episodes = json.loads((args.work_dir / "plan.json").read_text())["episodes"]
        if episodes:  # ManiSkill's replay divides by the episode count
            _replay(args.work_dir, args.obs_mode, args.control_mode, args.reward_mode)
    return 0


if __name__ == "__main__":
    sys.exit(main())
