"""Motion-planning solutions of our own, used instead of ManiSkill's where its demonstrations fall short.

PushCube: ManiSkill's solution (``mani_skill.examples.motionplanning.panda.solutions.push_cube``)
stops pushing with the cube 8.4-9.6 cm from the goal's centre (100 demos), within a few mm of the
10 cm success radius. A policy imitating it stops about there too, and its failures end just
short of the radius. Ours pushes up to 5 cm further, so that the cube ends well inside the goal
region. With the cube far from the robot (x above about 6 cm) the full 5 cm is out of a direct
push's reach: the screw planner finds no path, or one through a wrist reconfiguration of hundreds of
steps (measured on the 21 seeds of 126 where a fixed 5 cm failed). Ours then pushes as deep as a
direct push reaches, in 1 cm steps down to ManiSkill's depth, so that the far cubes keep their
demonstrations: without them the policy failed mostly there.

:data:`SOLUTION_TAGS` names each replaced solution; the demonstration cache keeps their plans apart
from ManiSkill's (``maniskill/<env_id>.<tag>/``). The solutions import ManiSkill when called.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SOLUTION_TAGS", "solution_for"]

#: env id -> the name of our solution (a cache key: change it when the solution changes)
SOLUTION_TAGS = {"PushCube-v1": "push5cm_direct"}

#: how much further than ManiSkill's solution ours pushes the cube (metres), deepest first: the
#: first whose plan is a direct push is taken
PUSH_FURTHER = (0.05, 0.04, 0.03, 0.02, 0.01, 0.0)
#: the longest push plan that is a direct motion (control steps): the push is always 13 cm plus its
#: depth, which direct plans cover in 33-50 steps; longer ones (77-970 measured) turn the wrist over
MAX_DIRECT_PUSH_STEPS = 60
#: PushCube plans longer than this are refused (counted as failed seeds), as the task's step limit
MAX_PUSH_PLAN_STEPS = 150


def _push_cube(env, seed=None, debug=False, vis=False):
    """Close the gripper, move 5 cm behind the cube, push it along x until the hand is 12 cm less
    the push depth short of the goal's centre (the cube's near face 2 cm ahead of the hand), at the
    deepest of :data:`PUSH_FURTHER` that a direct plan reaches."""
    # optional dependency: the simulator and its planner (maniskill extra), in the planner's process
    import sapien
    from mani_skill.examples.motionplanning.panda.motionplanner import PandaArmMotionPlanningSolver

    env.reset(seed=seed)
    planner = PandaArmMotionPlanningSolver(
        env, debug=debug, vis=vis, base_pose=env.unwrapped.agent.robot.pose, print_env_info=False
    )
    base = env.unwrapped
    planner.close_gripper()
    hand_q = base.agent.tcp.pose.sp.q
    behind = base.obj.pose.sp.p + np.array([-0.05, 0, 0])
    result = planner.move_to_pose_with_screw(sapien.Pose(p=behind, q=hand_q))
    if result != -1:
        result = -1
        for further in PUSH_FURTHER:
            goal = base.goal_region.pose.sp.p + np.array([-0.12 + further, 0, 0])
            plan = planner.move_to_pose_with_screw(sapien.Pose(p=goal, q=hand_q), dry_run=True)
            if plan != -1 and len(plan["position"]) <= MAX_DIRECT_PUSH_STEPS:
                result = planner.follow_path(plan)
                break
    planner.close()
    if result != -1 and int(base.elapsed_steps.max()) > MAX_PUSH_PLAN_STEPS:
        return -1  # the worker records a seed whose plan is refused like one without a path
    return result


def solution_for(env_id: str):
    """Our solution for ``env_id``, else ManiSkill's; None when neither exists."""
    if env_id == "PushCube-v1":
        return _push_cube
    from mani_skill.examples.motionplanning.panda.run import MP_SOLUTIONS  # optional: maniskill extra

    return MP_SOLUTIONS.get(env_id)
