"""Scripted pick-and-place experts for robosuite's Lift, Stack, PickPlaceCan, NutAssemblySquare and
ToolHang, written against privileged simulator state (object poses from MuJoCo, the end effector from
the observation).

An expert is a list of phases (move above the object, descend, close, lift, carry, release, ...).
Each phase's target is computed from the live object poses when the phase starts, and the
commanded pose walks towards it at a bounded speed, so actions are smooth absolute OSC_POSE
targets [x, y, z, axis-angle, gripper]. Every episode draws its own speed, grasp offset, heights,
yaw jitter and gripper timing from its seed, so that the demonstrations are not one trajectory.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

__all__ = ["EXPERT_TASKS", "Phase", "PosePhase", "ScriptedExpert", "canonical_rotvec", "make_expert"]

OPEN, CLOSED = -1.0, 1.0

#: the half-space the absolute actions' axis-angle is kept in (see :func:`canonical_rotvec`)
_ROTVEC_REFERENCE = np.array([-1.0, 0.0, 0.0])


def _up(height: float) -> np.ndarray:
    return np.array([0.0, 0.0, height])


def canonical_rotvec(rotation: Rotation) -> np.ndarray:
    """Axis-angle of ``rotation`` with a positive component along (-1, 0, 0).

    A top-down gripper is a rotation by ~pi, where axis-angle is ambiguous (r and r - 2 pi r/|r|
    are the same rotation); scipy picks either side, which would make the recorded actions jump
    by ~2 pi between steps. Keeping one side makes them continuous for yaws within +-180 deg of
    the robot's home pose.
    """
    r = rotation.as_rotvec()
    angle = float(np.linalg.norm(r))
    if angle > 1e-6 and float(r @ _ROTVEC_REFERENCE) < 0:
        r = r - 2 * np.pi * r / angle
    return r


def body_yaw(env, body_id: int) -> float:
    """A MuJoCo body's yaw in the world (radians about the vertical)."""
    w, x, y, z = env.sim.data.body_xquat[body_id]
    return float(Rotation.from_quat([x, y, z, w]).as_euler("xyz")[2])


@dataclass
class Phase:
    """Move the commanded position to ``target()`` (evaluated when the phase starts) with the
    gripper at ``gripper``; done once the end effector is within ``tol`` of it and ``hold`` more
    steps have passed (closing fingers need them)."""

    name: str
    target: Callable[[], np.ndarray]
    gripper: float
    tol: float = 0.01
    hold: int = 0
    speed_scale: float = 1.0
    #: a new gripper yaw goal (radians from the home pose), evaluated when the phase starts; the
    #: phase then also waits for the commanded yaw to reach it
    yaw: Callable[[], float] | None = None
    #: once the command has reached the target, shift it by the end effector's remaining error
    #: (integral action): OSC lags 1-2 cm at the edge of the reach, more than a peg's clearance
    servo: bool = False


class ScriptedExpert:
    """Runs phases on a robosuite env whose arm takes absolute world-frame OSC_POSE targets."""

    #: a phase that has not converged after this many steps has failed (the object slipped, ...)
    PHASE_TIMEOUT = 120

    def __init__(self, env, rng: np.random.Generator) -> None:
        self.env, self.rng = env, rng
        self.speed = rng.uniform(0.012, 0.022)  # metres per control step (20 Hz): 0.24-0.44 m/s
        self.phases: list[Phase] = []
        self._phase = 0
        self._started = False
        self._target = np.zeros(3)
        self._elapsed = 0
        self._held = 0
        self._cmd_pos: np.ndarray | None = None
        self._cmd_yaw = 0.0
        self._yaw_goal = 0.0
        self._bias = np.zeros(3)  # the servo phases' correction, added to every later command
        self._home: Rotation | None = None
        self._gripper = OPEN
        self.failed = False

    # -- privileged state --------------------------------------------------------------------------

    def eef_pos(self) -> np.ndarray:
        robot = self.env.robots[0]
        return np.array(self.env.sim.data.site_xpos[robot.eef_site_id["right"]])

    def body_pos(self, body_id: int) -> np.ndarray:
        return np.array(self.env.sim.data.body_xpos[body_id])

    def body_yaw(self, body_id: int) -> float:
        return body_yaw(self.env, body_id)

    def eef_rotation(self) -> Rotation:
        robot = self.env.robots[0]
        mat = np.array(self.env.sim.data.site_xmat[robot.eef_site_id["right"]]).reshape(3, 3)
        return Rotation.from_matrix(mat)

    def align_yaw(self, object_yaw: float, symmetry: float) -> None:
        """Turn the gripper about the vertical so that its fingers meet the object's faces (the
        object looks the same every ``symmetry`` radians), plus a little jitter."""
        home_yaw = float(self._home.as_euler("xyz")[2]) if self._home is not None else 0.0
        delta = (object_yaw - home_yaw + symmetry / 2) % symmetry - symmetry / 2
        self._yaw_goal = delta + self.rng.uniform(-0.08, 0.08)

    # -- control -----------------------------------------------------------------------------------

    def reset(self) -> None:
        self._cmd_pos = self.eef_pos()
        self._home = self.eef_rotation()
        self.phases = self.plan()

    def plan(self) -> list[Phase]:
        raise NotImplementedError

    @property
    def done(self) -> bool:
        return self._phase >= len(self.phases)

    def act(self) -> np.ndarray:
        """The next action; after the last phase it holds the last command."""
        if not self.done:
            phase = self.phases[self._phase]
            if not self._started:
                self._target, self._started = np.asarray(phase.target(), dtype=float), True
                self._elapsed = self._held = 0
                if phase.yaw is not None:
                    self._yaw_goal = float(phase.yaw())
            self._gripper = phase.gripper
            step = self._target - self._cmd_pos
            dist = float(np.linalg.norm(step))
            max_step = self.speed * phase.speed_scale
            self._cmd_pos = self._cmd_pos + (step if dist <= max_step else step * max_step / dist)
            self._elapsed += 1
            if phase.servo and dist <= max_step:
                error = self._target - self.eef_pos()
                self._bias = np.clip(self._bias + np.clip(0.1 * error, -0.002, 0.002), -0.04, 0.04)
            turned = abs(self._yaw_goal - self._cmd_yaw) < 1e-6 or phase.yaw is None
            if np.linalg.norm(self.eef_pos() - self._target) < phase.tol and dist <= max_step and turned:
                self._held += 1
                if self._held > phase.hold:
                    self._phase, self._started = self._phase + 1, False
            elif self._elapsed > self.PHASE_TIMEOUT:
                self.failed = True
        self._cmd_yaw += float(np.clip(self._yaw_goal - self._cmd_yaw, -0.08, 0.08))
        rotation = Rotation.from_euler("z", self._cmd_yaw) * self._home
        return np.concatenate([self._cmd_pos + self._bias, canonical_rotvec(rotation), [self._gripper]])


class LiftExpert(ScriptedExpert):
    """Above the cube, down, close, lift (robosuite's success: the cube 4 cm above the table)."""

    def plan(self) -> list[Phase]:
        env, rng = self.env, self.rng
        cube = env.cube_body_id
        self.align_yaw(self.body_yaw(cube), np.pi / 2)
        grasp = np.array([*rng.uniform(-0.006, 0.006, 2), rng.uniform(-0.012, 0.0)])
        above = rng.uniform(0.05, 0.12)
        return [
            Phase("above", lambda: self.body_pos(cube) + grasp + [0, 0, above], OPEN, tol=0.02),
            Phase("descend", lambda: self.body_pos(cube) + grasp, OPEN, tol=0.008, speed_scale=0.6),
            Phase("close", lambda: self._cmd_pos, CLOSED, tol=0.02, hold=int(rng.integers(5, 9))),
            Phase("lift", lambda: self._cmd_pos + _up(rng.uniform(0.12, 0.2)), CLOSED, tol=0.03),
        ]


class StackExpert(ScriptedExpert):
    """Pick cube A, carry it above cube B, lower it onto B, open and back off."""

    def plan(self) -> list[Phase]:
        env, rng = self.env, self.rng
        a, b = env.cubeA_body_id, env.cubeB_body_id
        self.align_yaw(self.body_yaw(a), np.pi / 2)
        grasp = np.array([*rng.uniform(-0.005, 0.005, 2), rng.uniform(-0.008, 0.0)])
        above = rng.uniform(0.05, 0.1)
        carry = rng.uniform(0.1, 0.16)
        # cube B's top is 2.5 cm above its centre; cube A's centre sits 2 cm above that
        drop = rng.uniform(0.047, 0.053)
        return [
            Phase("above_a", lambda: self.body_pos(a) + grasp + [0, 0, above], OPEN, tol=0.02),
            Phase("descend", lambda: self.body_pos(a) + grasp, OPEN, tol=0.008, speed_scale=0.6),
            Phase("close", lambda: self._cmd_pos, CLOSED, tol=0.02, hold=int(rng.integers(5, 9))),
            Phase("lift", lambda: self._cmd_pos + _up(carry), CLOSED, tol=0.03),
            Phase(
                "above_b",
                lambda: self.body_pos(b) + self._grip_offset(a) + [0, 0, drop + 0.05],
                CLOSED,
                tol=0.012,
            ),
            Phase(
                "lower",
                lambda: self.body_pos(b) + self._grip_offset(a) + [0, 0, drop],
                CLOSED,
                tol=0.01,
                speed_scale=0.4,
            ),
            Phase("open", lambda: self._cmd_pos, OPEN, tol=0.03, hold=int(rng.integers(3, 7))),
            Phase("retreat", lambda: self._cmd_pos + _up(0.08), OPEN, tol=0.03),
        ]

    def _grip_offset(self, body_id: int) -> np.ndarray:
        """Where the end effector is relative to the held object (so the object, not the gripper,
        lands on the target)."""
        return self.eef_pos() - self.body_pos(body_id)


class CanExpert(ScriptedExpert):
    """Pick the can from the left bin and drop it into its compartment of the right bin."""

    def plan(self) -> list[Phase]:
        env, rng = self.env, self.rng
        can = env.obj_body_id["Can"]
        goal = np.array(env.target_bin_placements[env.object_to_id["can"]], dtype=float)
        # the fingers close around the can's upper half: lower, they meet it before their target
        grasp = np.array([*rng.uniform(-0.004, 0.004, 2), rng.uniform(0.0, 0.02)])
        above = rng.uniform(0.06, 0.12)
        # the far compartment is near the arm's reach: carry low, and accept a few cm of lag there
        carry_z = env.bin2_pos[2] + rng.uniform(0.16, 0.2)
        release_z = env.bin2_pos[2] + rng.uniform(0.1, 0.13)
        # aim at the compartment's near part (it spans ~20 x 25 cm): its centre is at the edge of reach
        jitter = np.array([-rng.uniform(0.02, 0.06), -rng.uniform(0.03, 0.07), 0.0])
        return [
            Phase("above", lambda: self.body_pos(can) + grasp + [0, 0, above], OPEN, tol=0.02),
            Phase("descend", lambda: self.body_pos(can) + grasp, OPEN, tol=0.012, speed_scale=0.6),
            Phase("close", lambda: self._cmd_pos, CLOSED, tol=0.02, hold=int(rng.integers(5, 9))),
            Phase("lift", lambda: np.array([*self._cmd_pos[:2], carry_z]), CLOSED, tol=0.03),
            Phase("carry", lambda: np.array([goal[0], goal[1], carry_z]) + jitter, CLOSED, tol=0.04),
            Phase("lower", lambda: np.array([goal[0], goal[1], release_z]) + jitter, CLOSED, tol=0.04),
            Phase("open", lambda: self._cmd_pos, OPEN, tol=0.05, hold=int(rng.integers(4, 8))),
            Phase("retreat", lambda: self._cmd_pos + _up(0.1), OPEN, tol=0.03),
        ]


class SquareExpert(ScriptedExpert):
    """Grasp the square nut by its handle, lift it, turn it square to the peg, carry it over the
    square peg and lower it down the peg (robosuite's success: the nut's centre within 3 cm of the
    peg's axis and below 5 cm above the table, the gripper away from the nut's centre)."""

    def plan(self) -> list[Phase]:
        env, rng = self.env, self.rng
        nut = env.obj_body_id[env.nuts[env.nut_id].name]
        handle = env.sim.model.site_name2id(env.nuts[env.nut_id].important_sites["handle"])
        peg = np.array(env.sim.data.body_xpos[env.peg1_body_id])
        # the fingers close across the handle (the nut's local y); at home they close along world y,
        # so the gripper turns by the nut's yaw (the handle looks the same every pi for the fingers)
        self.align_yaw(self.body_yaw(nut) + np.pi / 2, np.pi)
        grasp_yaw = self._yaw_goal
        # along the handle (away from the nut's frame) and across it, in the nut's frame
        along, across = rng.uniform(0.002, 0.012), rng.uniform(-0.003, 0.003)
        depth = rng.uniform(-0.002, 0.004)  # lower, the tilted hand's far finger meets the table
        above = rng.uniform(0.05, 0.1)
        carry_z = peg[2] + rng.uniform(0.17, 0.22)  # the peg's top is 10 cm above its centre
        lower_speed = rng.uniform(0.3, 0.5)
        peg_top = peg[2] + 0.1  # the peg is a 20 cm box about its centre
        drop = rng.uniform(0.025, 0.04)

        def grasp_point() -> np.ndarray:
            yaw = self.body_yaw(nut)
            axis, side = np.array([np.cos(yaw), np.sin(yaw), 0.0]), np.array([-np.sin(yaw), np.cos(yaw), 0.0])
            return np.array(env.sim.data.site_xpos[handle]) + along * axis + across * side + _up(depth)

        def square_yaw() -> float:
            # the nut's yaw is turned to a multiple of pi/2 (the peg's faces), by the smallest turn
            # that keeps the gripper within 45 deg of its home yaw
            final = self._cmd_yaw - self.body_yaw(nut)
            return (final + np.pi / 4) % (np.pi / 2) - np.pi / 4 + rng.uniform(-0.03, 0.03)

        def over_peg(nut_z: float) -> np.ndarray:
            offset = self.eef_pos() - self.body_pos(nut)  # where the hand holds the nut
            return np.array([peg[0] + offset[0], peg[1] + offset[1], nut_z + offset[2]])

        return [
            Phase("above", lambda: grasp_point() + _up(above), OPEN, tol=0.02, yaw=lambda: grasp_yaw),
            Phase("descend", grasp_point, OPEN, tol=0.008, speed_scale=0.5),
            Phase("close", lambda: self._cmd_pos, CLOSED, tol=0.02, hold=int(rng.integers(5, 9))),
            Phase("lift", lambda: np.array([*self._cmd_pos[:2], carry_z]), CLOSED, tol=0.03),
            Phase("turn", lambda: self._cmd_pos, CLOSED, tol=0.03, hold=3, yaw=square_yaw),
            Phase("over_peg", lambda: over_peg(carry_z), CLOSED, tol=0.01, servo=True),
            Phase("settle", lambda: over_peg(carry_z), CLOSED, tol=0.004, hold=6, servo=True),
            # released a few cm down the peg, before the hand meets the peg's top: the nut drops the rest
            Phase("lower", lambda: over_peg(peg_top - drop), CLOSED, tol=0.015, speed_scale=lower_speed),
            Phase("open", lambda: self._cmd_pos, OPEN, tol=0.05, hold=int(rng.integers(3, 7))),
            Phase("retreat", lambda: self._cmd_pos + _up(0.08), OPEN, tol=0.03),
        ]


@dataclass
class PosePhase(Phase):
    """A :class:`Phase` with a full gripper orientation and a tracked point (ToolHang's expert turns
    the hand off the vertical, and place a held object's point rather than the hand)."""

    #: the gripper's world orientation goal, evaluated when the phase starts (None: keep turning
    #: towards the previous goal)
    rotation: Callable[[], Rotation] | None = None
    #: the point that must reach ``target`` (default: the end effector), e.g. the frame's tip
    track: Callable[[], np.ndarray] | None = None
    #: radians per control step the commanded orientation turns by
    turn: float = 0.04


class ToolHangExpert(ScriptedExpert):
    """Insert the hook frame into the stand's hole, then hang the tool's large ring on the hook.

    The frame lies flat with its grip up: the hand grasps the grip top-down with the fingers along
    the frame's bar, and turns the whole frame about the finger axis until its rod is vertical
    (measured on the held frame, so the grasp's own tilt is corrected). The bar ends pointing from
    the hook to the rod along -y, so that the hand points forward (+x). The other directions fail:
    along +x the hook comes so near the robot's base that the elbow folds to its limit when the tool
    is brought there; along +y the hand points back at the robot and the stretched arm cannot
    leave the frame; diagonally the square rod (0.75 cm) jams in the square bore (1 cm). The rod's
    tip is servoed over the bore and pushed down to the base.

    The ring cannot slide along the bar onto the hook: its bore (an octagon 19.4 mm across the
    flats) is narrower than the hook's end (the bar and its 1.2 cm upright: 19.5 mm tall). So the
    tool is held nearly flat (ring axis ~75 deg from the bar) with the ring over the hook's upright,
    lowered around it and let go: it drops onto the bar and swings down to hang (in teleported
    drops, for ring centres within ~+-3 mm of the upright).
    """

    PHASE_TIMEOUT = 150

    def __init__(self, env, rng: np.random.Generator) -> None:
        super().__init__(env, rng)
        self.speed = rng.uniform(0.010, 0.016)  # slower than the pick-and-place experts: 0.2-0.32 m/s
        self._cmd_rot = Rotation.identity()
        self._rot_goal = Rotation.identity()
        self._goal = np.zeros(3)
        self._offset = np.zeros(3)
        self._last_rotvec: np.ndarray | None = None
        self._frame_grasp = Rotation.identity()

    # -- privileged state --------------------------------------------------------------------------

    def site(self, name: str) -> np.ndarray:
        return np.array(self.env.sim.data.site_xpos[self.env.sim.model.site_name2id(name)])

    def geom(self, name: str) -> np.ndarray:
        return np.array(self.env.sim.data.geom_xpos[self.env.sim.model.geom_name2id(name)])

    def body_rotation(self, body_id: int) -> Rotation:
        return Rotation.from_matrix(np.array(self.env.sim.data.body_xmat[body_id]).reshape(3, 3))

    def _holding(self, body_id: int) -> Rotation:
        """The hand's orientation in the held object's frame (what a turn of the hand turns it by)."""
        return self.body_rotation(body_id).inv() * self.eef_rotation()

    @staticmethod
    def _top_down(finger_axis: np.ndarray) -> Rotation:
        """A gripper pointing straight down with its fingers closing along ``finger_axis``."""
        gx = np.array([finger_axis[0], finger_axis[1], 0.0])
        gx /= np.linalg.norm(gx)
        down = np.array([0.0, 0.0, -1.0])
        return Rotation.from_matrix(np.column_stack([gx, np.cross(down, gx), down]))

    # -- plan --------------------------------------------------------------------------------------

    def reset(self) -> None:
        self._cmd_rot = self._rot_goal = self.eef_rotation()
        super().reset()

    def plan(self) -> list[Phase]:
        return self.frame_phases() + self.tool_phases()

    def frame_phases(self) -> list[Phase]:
        env, rng, model = self.env, self.rng, self.env.sim.model
        frame = env.obj_body_id["frame"]
        up = np.array([0.0, 0.0, 1.0])
        # the bore: between the stand's four walls, its mouth at the walls' top
        walls = np.array([self.geom(f"stand_wall{i}") for i in range(4)])
        hole = walls.mean(axis=0)
        mouth = hole[2] + model.geom_size[model.geom_name2id("stand_wall0")][2]
        base_top = self.geom("stand_base")[2] + model.geom_size[model.geom_name2id("stand_base")][2]
        bar = np.array([0.0, -1.0, 0.0])  # from the hook to the rod, once assembled
        side = np.cross(up, bar)  # the hand's pointing direction once the frame is upright
        upright = Rotation.from_matrix(np.column_stack([bar, np.cross(up, bar), up]))  # frame axes
        # fingers along the bar (the frame's x) close across the grip
        self._frame_grasp = Rotation.from_euler("z", rng.uniform(-0.04, 0.04)) * self._top_down(
            self.body_rotation(frame).as_matrix()[:, 0]
        )
        grasp = np.array([*rng.uniform(-0.002, 0.002, 2), rng.uniform(0.0, 0.006)])
        above = rng.uniform(0.06, 0.1)
        lift_z = mouth + rng.uniform(0.24, 0.28)  # the tip hangs ~21 cm below the grip
        self._lift_z = lift_z

        def grip() -> np.ndarray:
            return self.geom("frame_grip_frame")

        def tip() -> np.ndarray:
            return self.site("frame_tip_site")

        def retreat() -> np.ndarray:
            # back along the hand's axis, off the grip: the fingers straddle the rod under the bar,
            # so lifting them would lift the frame out of the stand
            away = np.sign((self.eef_pos() - grip()) @ side) or 1.0
            return self._cmd_pos + 0.06 * away * side

        return [
            PosePhase(
                "above",
                lambda: grip() + grasp + _up(above),
                OPEN,
                tol=0.02,
                rotation=lambda: self._frame_grasp,
            ),
            PosePhase("descend", lambda: grip() + grasp, OPEN, tol=0.008, speed_scale=0.5),
            PosePhase("close", lambda: self._cmd_pos, CLOSED, tol=0.02, hold=int(rng.integers(6, 10))),
            PosePhase("lift", lambda: np.array([*self._cmd_pos[:2], lift_z]), CLOSED, tol=0.03),
            PosePhase(
                "upright",
                lambda: np.array([hole[0], hole[1], lift_z]) - 0.05 * side,
                CLOSED,
                tol=0.03,
                rotation=lambda: upright * self._holding(frame),
                turn=0.03,
            ),
            PosePhase(
                "over_hole",
                lambda: hole * [1, 1, 0] + _up(mouth + 0.04),
                CLOSED,
                tol=0.01,
                track=tip,
                servo=True,
            ),
            PosePhase(
                "settle",
                lambda: hole * [1, 1, 0] + _up(mouth + 0.02),
                CLOSED,
                tol=0.003,
                hold=5,
                track=tip,
                servo=True,
                speed_scale=0.3,
            ),
            # down to the base (the rod binds a little in the bore: accept 1.2 cm short, it drops)
            PosePhase(
                "insert",
                lambda: hole * [1, 1, 0] + _up(base_top + 0.002),
                CLOSED,
                tol=0.012,
                track=tip,
                speed_scale=0.3,
            ),
            PosePhase("open", lambda: self._cmd_pos, OPEN, tol=0.05, hold=int(rng.integers(4, 8))),
            PosePhase("back", retreat, OPEN, tol=0.025),
        ]

    def tool_phases(self) -> list[Phase]:
        env, rng = self.env, self.rng
        tool = env.obj_body_id["tool"]
        up = np.array([0.0, 0.0, 1.0])
        # the ring's axis 75 deg from the bar, and the tool turned 15 deg about the vertical: nearly
        # flat, so that it drops round the hook's upright; the turn keeps the hand's last joint off
        # its limit (the ring must turn ~150 deg from where the tool lies). Fixed, not drawn: where
        # the dropped ring lands is sensitive to them (drawn a few degrees and a millimetre around
        # these, the expert succeeded less often)
        tilt, psi = np.radians(75.0), np.radians(15.0)
        # the ring's centre from the bar's end, over the upright (7.5 mm long). The failures leave the
        # ring caught on the upright, short of it along the bar and above it: 5.5 mm along succeeds
        # more often than 4.5 mm on the same seeds (the expert's rate:
        # benchmarks/results/robosuite_experts.json)
        along = 0.0055
        held: dict[str, Rotation] = {}

        def ring() -> np.ndarray:
            return self.site("tool_hole1_center")

        def bar() -> tuple[np.ndarray, np.ndarray]:
            end, corner = self.site("frame_hang_site"), self.site("frame_intersection_site")
            u = (corner - end) * [1, 1, 0]
            return end, u / np.linalg.norm(u)

        def tool_goal() -> Rotation:
            # hanging: handle down (tool x), ring axis (tool z) along the bar; then tilted flat
            _, u = bar()
            hanging = Rotation.from_matrix(np.column_stack([-up, np.cross(-u, -up), -u]))
            return Rotation.from_euler("z", psi) * Rotation.from_rotvec(np.cross(up, u) * tilt) * hanging

        def tool_grasp() -> Rotation:
            # fingers across the tool's grip: of the two (symmetric) grasps, the one whose finger
            # axis ends along +x; the other winds the last joint past its limit on the way
            axes = self.body_rotation(tool).as_matrix()
            grasps = [self._top_down(sign * axes[:, 1]) for sign in (1.0, -1.0)]
            ends = [(tool_goal() * self.body_rotation(tool).inv() * g).as_matrix()[0, 0] for g in grasps]
            return grasps[int(np.argmax(ends))]

        def holding() -> Rotation:
            held["rel"] = self._holding(tool)
            return self.eef_rotation()

        def over_hook(height: float) -> Callable[[], np.ndarray]:
            def point() -> np.ndarray:
                end, u = bar()
                return end + along * u + _up(height)

            return point

        def front() -> np.ndarray:
            return over_hook(0.1)() + 0.12 * bar()[1]

        return [
            PosePhase("up", lambda: self._cmd_pos + _up(0.1), OPEN, tol=0.03),
            # back the way the hand came (straight to a top-down pose drives the wrist into its limits)
            PosePhase(
                "unturn",
                lambda: self._cmd_pos + _up(0.03),
                OPEN,
                tol=0.03,
                rotation=lambda: self._frame_grasp,
                turn=0.05,
            ),
            PosePhase(
                "above_tool",
                lambda: self.body_pos(tool) + _up(0.1),
                OPEN,
                tol=0.02,
                rotation=tool_grasp,
                turn=0.05,
            ),
            PosePhase(
                "descend_tool",
                lambda: self.body_pos(tool) + _up(rng.uniform(0.0, 0.004)),
                OPEN,
                tol=0.008,
                speed_scale=0.5,
            ),
            PosePhase("close_tool", lambda: self._cmd_pos, CLOSED, tol=0.02, hold=int(rng.integers(6, 10))),
            PosePhase(
                "lift_tool",
                lambda: np.array([*self._cmd_pos[:2], self._lift_z - 0.02]),
                CLOSED,
                tol=0.03,
                rotation=holding,
            ),
            PosePhase(
                "turn_tool",
                front,
                CLOSED,
                tol=0.02,
                track=ring,
                rotation=lambda: tool_goal() * held["rel"],
                turn=0.04,
            ),
            # the tool may have turned in the fingers: measure the grasp again
            PosePhase(
                "regrasp",
                front,
                CLOSED,
                tol=0.02,
                track=ring,
                rotation=lambda: (holding(), tool_goal() * held["rel"])[1],
            ),
            PosePhase("over_hook", over_hook(0.035), CLOSED, tol=0.004, hold=4, track=ring, servo=True),
            PosePhase(
                "lower_tool",
                over_hook(0.012),
                CLOSED,
                tol=0.004,
                hold=3,
                track=ring,
                servo=True,
                speed_scale=0.4,
            ),
            PosePhase("release", lambda: self._cmd_pos, OPEN, tol=0.05, hold=int(rng.integers(4, 8))),
            PosePhase("away", lambda: self._cmd_pos + _up(0.06) - np.array([0.05, 0, 0]), OPEN, tol=0.03),
        ]

    # -- control -----------------------------------------------------------------------------------

    def act(self) -> np.ndarray:
        if not self.done:
            phase = self.phases[self._phase]
            track = getattr(phase, "track", None) or self.eef_pos
            rotation = getattr(phase, "rotation", None)
            if not self._started:
                self._goal, self._started = np.asarray(phase.target(), dtype=float), True
                if getattr(phase, "track", None) is None and not phase.servo:
                    # the servo's correction was for the point it tracked: fold it into the command
                    self._cmd_pos, self._bias = self._cmd_pos + self._bias, np.zeros(3)
                self._offset = track() - self.eef_pos()
                self._elapsed = self._held = 0
                if rotation is not None:
                    self._rot_goal = rotation()
            if rotation is not None and getattr(phase, "track", None) is not None:
                # the tracked point swings round the hand while it turns: follow it
                self._offset = track() - self.eef_pos()
            self._target = self._goal - self._offset
            self._gripper = phase.gripper
            step = self._target - self._cmd_pos
            dist = float(np.linalg.norm(step))
            max_step = self.speed * phase.speed_scale
            self._cmd_pos = self._cmd_pos + (step if dist <= max_step else step * max_step / dist)
            self._elapsed += 1
            if phase.servo and dist <= max_step:
                error = self._goal - track()
                self._bias = np.clip(self._bias + np.clip(0.1 * error, -0.002, 0.002), -0.04, 0.04)
            turn = getattr(phase, "turn", 0.04)
            angle = (self._rot_goal * self._cmd_rot.inv()).magnitude()
            if angle > 1e-9:
                slerp = Slerp([0.0, 1.0], Rotation.concatenate([self._cmd_rot, self._rot_goal]))
                self._cmd_rot = slerp([min(1.0, turn / angle)])[0]
            if np.linalg.norm(track() - self._goal) < phase.tol and dist <= max_step and angle <= turn:
                self._held += 1
                if self._held > phase.hold:
                    self._phase, self._started = self._phase + 1, False
            elif self._elapsed > self.PHASE_TIMEOUT:
                self.failed = True
        return np.concatenate([self._cmd_pos + self._bias, self._continuous_rotvec(), [self._gripper]])

    def _continuous_rotvec(self) -> np.ndarray:
        """The commanded orientation's axis-angle, on whichever side (r or r - 2 pi r/|r|, the same
        rotation) is nearer the previous action's: the hand turns through many poses here, so the
        fixed half-space of :func:`canonical_rotvec` need not keep the actions continuous."""
        r = canonical_rotvec(self._cmd_rot)
        angle = float(np.linalg.norm(r))
        if self._last_rotvec is not None and angle > 1e-6:
            other = r - 2 * np.pi * r / angle
            if np.linalg.norm(other - self._last_rotvec) < np.linalg.norm(r - self._last_rotvec):
                r = other
        self._last_rotvec = r
        return r


#: env ids the scripted experts solve
EXPERT_TASKS: dict[str, type[ScriptedExpert]] = {
    "Lift": LiftExpert,
    "Stack": StackExpert,
    "PickPlaceCan": CanExpert,
    "NutAssemblySquare": SquareExpert,
    "ToolHang": ToolHangExpert,
}


def make_expert(env_id: str, env, rng: np.random.Generator) -> ScriptedExpert:
    try:
        cls = EXPERT_TASKS[env_id]
    except KeyError:
        raise ValueError(
            f"no scripted robosuite expert for {env_id!r}; experts exist for {sorted(EXPERT_TASKS)}"
        ) from None
    return cls(env, rng)
