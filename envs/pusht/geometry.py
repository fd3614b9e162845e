"""PushT's geometry, shared by the env adapter, the scripted expert and the zarr writer: the T in its
own frame, the goal pose, Diffusion Policy's block keypoints, and the state fix that makes
gym-pusht's ``reset_to_state`` reproduce an observed state. Pure numpy; no simulator import."""

from __future__ import annotations

import os

import numpy as np

__all__ = [
    "AGENT_RADIUS",
    "BLOCK_COG",
    "DP_BLOCK_KEYPOINTS",
    "GOAL_POSE",
    "T_CORNERS",
    "T_RECTANGLES",
    "block_keypoints",
    "compute_dp_block_keypoints",
    "reset_state_for",
    "to_world",
]

#: the goal pose of the block: x, y, angle (gym-pusht's ``goal_pose``)
GOAL_POSE = np.array([256.0, 256.0, np.pi / 4])
#: the agent is a disc of this radius
AGENT_RADIUS = 15.0
#: the T's two rectangles in the block frame (gym-pusht's ``add_tee`` with scale 30, length 4):
#: the bar (120 x 30) and the stem (30 x 90) below it
T_RECTANGLES = (
    np.array([[-60.0, 0.0], [60.0, 0.0], [60.0, 30.0], [-60.0, 30.0]]),
    np.array([[-15.0, 30.0], [15.0, 30.0], [15.0, 120.0], [-15.0, 120.0]]),
)
#: the T's outline, in order around it (block frame)
T_CORNERS = np.array(
    [[-60, 0], [60, 0], [60, 30], [15, 30], [15, 120], [-15, 120], [-15, 30], [-60, 30]], dtype=np.float64
)
#: the block's centre of gravity in its frame (the mean of the two rectangles' centroids)
BLOCK_COG = np.array([0.0, 45.0])

#: Diffusion Policy's 9 block keypoints in the block frame (``PymunkKeypointManager`` with seed 0:
#: farthest-point sampling over the rendered T plus a uniform shift); ``compute_dp_block_keypoints``
#: recomputes them and a test checks the two agree.
DP_BLOCK_KEYPOINTS = np.array(
    [
        [9.2697867138, 90.0409735239],
        [-60.9834723645, -1.1867297608],
        [60.9127555773, -1.3933642242],
        [-0.270503439, 25.5436249915],
        [-14.0649275762, 122.8158535541],
        [39.0027385002, 32.8574042766],
        [-39.9664144247, 32.7296554464],
        [-16.8243443794, 62.8631789223],
        [23.5414612202, -1.7002881095],
    ]
)


def to_world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Block-frame points [..., K, 2] -> world, for poses [..., 3] (x, y, angle)."""
    pose = np.asarray(pose, dtype=np.float64)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # [..., 2, 2]
    return np.einsum("...ij,kj->...ki", rot, np.asarray(points, dtype=np.float64)) + pose[..., None, :2]


def block_keypoints(state: np.ndarray) -> np.ndarray:
    """Diffusion Policy's keypoints [..., 9, 2] of the block, from gym-pusht states [..., 5]."""
    state = np.asarray(state, dtype=np.float64)
    return to_world(DP_BLOCK_KEYPOINTS, state[..., 2:5])


def reset_state_for(state: np.ndarray) -> np.ndarray:
    """The ``reset_to_state`` value that makes gym-pusht's env observe ``state`` (5-D) after reset.

    gym-pusht (0.1.8) keeps its legacy setter: it places the block's origin, then sets the angle about
    the centre of gravity, which moves the origin by ``(I - R(angle)) @ cog``. Passing an observed
    state back therefore shifts the block by up to 90 px; this undoes the shift, so that a recorded
    ``data/state[0]`` reproduces its episode's start (Diffusion Policy's own env sets the angle first
    and needs no fix).
    """
    state = np.asarray(state, dtype=np.float64).copy()
    angle = state[..., 4]
    c, s = np.cos(angle), np.sin(angle)
    rotated_cog = np.stack([c * BLOCK_COG[0] - s * BLOCK_COG[1], s * BLOCK_COG[0] + c * BLOCK_COG[1]], -1)
    state[..., 2:4] = state[..., 2:4] - BLOCK_COG + rotated_cog
    return state


def compute_dp_block_keypoints(seed: int = 0, count: int = 9) -> np.ndarray:
    """Diffusion Policy's recipe for the block keypoints, recomputed: render the T at (256, 300),
    angle 0, with gym-pusht's drawing code; farthest-point-sample ``count`` of its pixels (first point
    drawn by ``default_rng(seed)``); add a U(0, 1) shift. Needs pygame and gym-pusht."""
    os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
    # optional dependency: the simulator (pusht extra)
    import pygame
    import pymunk
    from gym_pusht.envs.pusht import PushTEnv
    from gym_pusht.envs.pymunk_override import DrawOptions

    rng = np.random.default_rng(seed)
    space = pymunk.Space()
    PushTEnv.add_tee(space, (256, 300), 0)
    screen = pygame.Surface((512, 512))
    screen.fill(pygame.Color("white"))
    space.debug_draw(DrawOptions(screen))
    image = pygame.surfarray.array3d(screen).transpose(1, 0, 2)
    ys, xs = np.nonzero((image != 255).any(-1))  # row-major, as Diffusion Policy reads its mask
    points = np.stack([xs, ys], -1).astype(np.float64) - np.array([256.0, 300.0])
    chosen = [int(rng.choice(len(points)))]
    nearest = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(nearest)))
        nearest = np.minimum(nearest, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return points[chosen] + rng.uniform(0, 1, size=(count, 2))
