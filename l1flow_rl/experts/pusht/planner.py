"""A scripted PushT expert: a push planner that looks ahead in a copy of gym-pusht's own physics.

Each round it scores candidate pushes (a contact point on the T's outline, a push direction and a
length) by simulating them in a scratch pymunk space from the block's current pose, keeps the few
that bring the T's corners closest to the goal per step spent, simulates those again with the path
that takes the agent to the contact point, and executes the best. The path goes straight when the
block is not in the way, else around the block on the left or the right (as seen from the agent in
the rendered image): where both ways are about as long, the episode's randomly drawn side decides,
so the demonstrations hold both modes (see :attr:`PushTPlanner.side`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from l1flow_rl.envs.pusht.geometry import (
    AGENT_RADIUS,
    BLOCK_COG,
    GOAL_POSE,
    T_CORNERS,
    T_RECTANGLES,
    to_world,
)

__all__ = ["Push", "PushTPlanner", "corner_error"]

SIDES = ("left", "right")
_DT, _SUBSTEPS, _KP, _KV = 0.01, 10, 100.0, 20.0  # gym-pusht's PD control: 10 substeps per action
_GOAL_CORNERS = to_world(T_CORNERS, GOAL_POSE)


def _contacts() -> list[tuple[np.ndarray, np.ndarray]]:
    """Contact points on the T's outline with their outward normals (block frame)."""
    out = []
    for x in (-50, -30, -10, 10, 30, 50):  # top of the bar
        out.append(((x, 0), (0, -1)))
    for s in (-1, 1):
        out.append(((60 * s, 15), (s, 0)))  # bar ends
        for x in (35, 50):  # under the bar, clear of the stem
            out.append(((x * s, 30), (0, 1)))
        for y in (60, 85, 110):  # stem sides
            out.append(((15 * s, y), (s, 0)))
    for x in (-8, 0, 8):  # stem foot
        out.append(((x, 120), (0, 1)))
    return [(np.array(p, float), np.array(n, float)) for p, n in out]


CONTACTS = _contacts()


def corner_error(pose: np.ndarray) -> float:
    """Root-mean-square distance (px) between the T's corners at ``pose`` and at the goal."""
    return float(np.sqrt(((to_world(T_CORNERS, pose) - _GOAL_CORNERS) ** 2).sum(-1).mean()))


@dataclass
class Push:
    """One planned move: action targets that take the agent to a contact and push."""

    actions: list[np.ndarray]
    side: str | None = None  # "left"/"right" when the path goes around the block by choice
    chosen: bool = False  # whether both sides were viable and the episode's side decided
    error: float = math.inf  # predicted corner error after it
    steps: int = 0


@dataclass
class PushTPlanner:
    """Plans pushes from gym-pusht's state (see the module docstring).

    Args:
        rng: draws the episode's preferred side and breaks ties.
        nav_speed: px per step the target moves along a path to a contact.
        margin: clearance (px) kept between the agent and the block while travelling.
    """

    rng: np.random.Generator
    nav_speed: float = 22.0
    margin: float = 10.0
    shortlist: int = 4
    side: str = field(init=False)
    first_choice: str | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        self.side = SIDES[int(self.rng.integers(2))]
        self._space = None

    # -- scratch physics ------------------------------------------------------------------------

    def _scratch(self, agent: np.ndarray, velocity: np.ndarray, pose: np.ndarray):
        # optional dependency: the simulator (pusht extra)
        import pymunk
        from gym_pusht.envs.pusht import PushTEnv

        space = pymunk.Space()
        space.gravity, space.damping = (0, 0), 0.0
        for a, b in (((5, 506), (5, 5)), ((5, 5), (506, 5)), ((506, 5), (506, 506)), ((5, 506), (506, 506))):
            space.add(pymunk.Segment(space.static_body, a, b, 2))
        body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        body.position = tuple(agent)
        body.velocity = tuple(velocity)
        space.add(body, pymunk.Circle(body, AGENT_RADIUS))
        block, _ = PushTEnv.add_tee(space, (256, 300), 0)
        block.angle = float(pose[2])  # angle first, then position: the pose is set exactly
        block.position = (float(pose[0]), float(pose[1]))
        return space, body, block

    @staticmethod
    def _run(space, agent, block, actions) -> np.ndarray:
        for target in actions:
            tx, ty = float(target[0]), float(target[1])
            for _ in range(_SUBSTEPS):
                vx, vy = agent.velocity
                px, py = agent.position
                agent.velocity = (
                    vx + (_KP * (tx - px) - _KV * vx) * _DT,
                    vy + (_KP * (ty - py) - _KV * vy) * _DT,
                )
                space.step(_DT)
        return np.array([*block.position, block.angle])

    def simulate(self, state: np.ndarray, velocity: np.ndarray, actions: list[np.ndarray]) -> np.ndarray:
        """The block pose after ``actions`` from gym-pusht state ``state`` (agent moving at ``velocity``)."""
        space, agent, block = self._scratch(state[:2], velocity, state[2:5])
        return self._run(space, agent, block, actions)

    # -- paths ----------------------------------------------------------------------------------

    def _clear(self, a: np.ndarray, b: np.ndarray, pose: np.ndarray, clearance: float | None = None) -> bool:
        """Whether the agent can move from a to b keeping ``clearance`` (default: radius + margin / 2)
        between its centre and the block."""
        # optional dependency: gym-pusht's geometry (pusht extra)
        from shapely.geometry import LineString, Polygon

        clearance = AGENT_RADIUS + self.margin * 0.5 if clearance is None else clearance
        line = LineString([tuple(a), tuple(b)])
        return all(line.distance(Polygon(to_world(rect, pose))) >= clearance for rect in T_RECTANGLES)

    def _arrives(self, a: np.ndarray, p: np.ndarray, pose: np.ndarray) -> bool:
        """Whether the last leg a -> p (p just off the block) stays clear until its final 4 px."""
        gap = float(np.linalg.norm(p - a))
        return gap < 4 or self._clear(a, p - (p - a) * 4 / gap, pose, AGENT_RADIUS + 1)

    def path(
        self, a: np.ndarray, p: np.ndarray, pose: np.ndarray
    ) -> tuple[list[np.ndarray], str | None, bool] | None:
        """Waypoints from the agent at ``a`` to the pre-contact point ``p``, the side taken around the
        block (None when straight) and whether that side was a free choice; None when no way is clear."""
        if self._arrives(a, p, pose):
            return [a, p], None, False
        centre = to_world(BLOCK_COG[None], pose)[0]
        radius = 77.0 + AGENT_RADIUS + self.margin
        ra, rp = a - centre, p - centre
        phi_a, phi_p = math.atan2(ra[1], ra[0]), math.atan2(rp[1], rp[0])
        ccw = (phi_p - phi_a) % (2 * math.pi)  # increasing atan2 angle = the agent's left in the image
        options = {}
        for side, sweep in (("left", ccw), ("right", ccw - 2 * math.pi)):
            n = max(2, int(abs(sweep) * radius / 30.0) + 1)
            arc = [
                centre + radius * np.array([math.cos(phi_a + sweep * i / n), math.sin(phi_a + sweep * i / n)])
                for i in range(n + 1)
            ]
            arc = [np.clip(w, AGENT_RADIUS, 512 - AGENT_RADIUS) for w in arc]
            start = [a] if np.linalg.norm(ra) >= radius else [a, arc[0]]
            points = start + arc[1:] + [p]
            legs = itertools.pairwise(points[1:-1])
            if all(self._clear(u, v, pose) for u, v in legs) and self._arrives(points[-2], p, pose):
                options[side] = (points, abs(sweep))
        if not options:
            return None
        if len(options) == 2:
            short, long_ = sorted(o[1] for o in options.values())
            if short > 0.55 * long_:  # both ways about as long: the episode's side decides
                return options[self.side][0], self.side, True
            side = min(options, key=lambda s: options[s][1])
            return options[side][0], side, False
        side = next(iter(options))
        return options[side][0], side, False

    def _travel(self, points: list[np.ndarray]) -> list[np.ndarray]:
        """Action targets that move along a polyline at ``nav_speed`` and wait 2 steps at its end."""
        targets, carry = [], 0.0
        for u, v in itertools.pairwise(points):
            seg = float(np.linalg.norm(v - u))
            d = self.nav_speed - carry
            while d < seg:
                targets.append(u + (v - u) * d / seg)
                d += self.nav_speed
            carry = seg - (d - self.nav_speed)
        return [*targets, points[-1], points[-1]]

    # -- planning -------------------------------------------------------------------------------

    def _pushes(self, pose: np.ndarray, lengths: tuple[float, ...]):
        for point, normal in CONTACTS:
            for tilt in (-0.5, 0.0, 0.5):
                c, s = math.cos(pose[2]), math.sin(pose[2])
                rot = np.array([[c, -s], [s, c]])
                world_point = rot @ point + pose[:2]
                world_normal = rot @ normal
                pre = world_point + world_normal * (AGENT_RADIUS + 3.0)
                if not (
                    AGENT_RADIUS <= pre[0] <= 512 - AGENT_RADIUS
                    and AGENT_RADIUS <= pre[1] <= 512 - AGENT_RADIUS
                ):
                    continue
                ct, st = math.cos(tilt), math.sin(tilt)
                direction = -np.array(
                    [ct * world_normal[0] - st * world_normal[1], st * world_normal[0] + ct * world_normal[1]]
                )
                for length in lengths:
                    k = max(1, math.ceil(length / 12.0))
                    push = [pre + direction * length * (i + 1) / k for i in range(k)]
                    push += [push[-1], push[-1]]  # hold: the agent lags its target by about 2 steps
                    if all(
                        AGENT_RADIUS <= q[0] <= 512 - AGENT_RADIUS
                        and AGENT_RADIUS <= q[1] <= 512 - AGENT_RADIUS
                        for q in push
                    ):
                        yield pre, push

    def plan(self, state: np.ndarray, velocity: np.ndarray) -> Push | None:
        """The next move from gym-pusht state ``state`` (5-D), or None when no push helps."""
        now = corner_error(state[2:5])
        for lengths in (
            (6.0, 15.0, 30.0) if now < 25 else (15.0, 35.0, 60.0),
            (4.0, 5.5, 8.0),
        ):  # 3 px of each is the approach gap
            move = self._plan(state, velocity, now, lengths)
            if move is not None:
                return move
        return None

    def _plan(self, state: np.ndarray, velocity: np.ndarray, now: float, lengths) -> Push | None:
        pose, agent = state[2:5], state[:2]
        ranked = []
        for pre, push in self._pushes(pose, lengths):
            after = corner_error(self.simulate(np.concatenate([pre, pose]), np.zeros(2), [pre, *push]))
            if after >= now - 0.02:
                continue
            travel = float(np.linalg.norm(pre - agent)) / self.nav_speed + 2
            ranked.append(((now - after) / (travel + len(push)), pre, push))
        ranked.sort(key=lambda r: -r[0])
        best, best_rate, tried = None, 0.0, 0
        for _, pre, push in ranked[: 6 * self.shortlist]:
            route = self.path(agent, pre, pose)
            if route is None:
                continue
            points, side, chosen = route
            actions = [*self._travel(points)[1:], *push]
            after = corner_error(self.simulate(state, velocity, actions))
            rate = (now - after) / len(actions)
            if after < now - 0.02 and rate > best_rate:
                best, best_rate = Push(actions, side, chosen, after, len(actions)), rate
            tried += 1
            if tried >= self.shortlist:
                break
        return best
