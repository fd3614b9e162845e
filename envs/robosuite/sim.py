"""robosuite itself: the headless GL backend, the import (with an install hint), the env keyword
arguments a task or a robomimic file asks for, restoring stored MuJoCo states, and the robomimic
observation of a step. Every robosuite call of this project goes through here."""

from __future__ import annotations

import copy
import glob
import json
import logging
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from l1flow_rl.config import TaskConfig

__all__ = [
    "INSTALL_HINT",
    "ROBOMIMIC_ENV_TYPE",
    "choose_gl",
    "controller_configs",
    "env_args_for_task",
    "image_key",
    "import_robosuite",
    "make_from_env_args",
    "observation_arrays",
    "recorded_control",
    "restore_state",
    "robomimic_obs",
    "seed_episode",
    "step",
]

INSTALL_HINT = (
    "pip install 'l1flow-rl[robosuite]' (robosuite==1.5.2 with mujoco==3.3.7); headless rendering needs "
    "EGL or OSMesa: ./install.sh robosuite (apt: libegl1 libgl1 libosmesa6)"
)

#: robomimic's ``EnvType.ROBOSUITE_TYPE``, written in ``env_args["type"]`` so robomimic reads our files
ROBOMIMIC_ENV_TYPE = 1

#: robomimic's low-dimensional keys that robosuite names differently
_ROBOSUITE_KEY = {"object": "object-state"}


def choose_gl() -> str:
    """EGL where a GPU device node exists, else OSMesa (software; EGL without a device fails or
    falls back to the same software rasteriser). A ``MUJOCO_GL`` set by the user wins."""
    if glob.glob("/dev/nvidia[0-9]*") or glob.glob("/dev/dri/renderD*"):
        return "egl"
    return "osmesa"


def import_robosuite():
    """``robosuite``, imported after ``MUJOCO_GL`` is set (it is read once, at import)."""
    os.environ.setdefault("MUJOCO_GL", choose_gl())
    if os.environ["MUJOCO_GL"] in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    logger = logging.getLogger("robosuite_logs")
    if not any(isinstance(f, _RoutineNoise) for f in logger.filters):
        logger.addFilter(_RoutineNoise())
    try:
        # optional dependency: the simulator (robosuite extra)
        import robosuite
    except ImportError as err:
        raise ImportError(f"robosuite is not importable ({err}): {INSTALL_HINT}") from err
    return robosuite


class _RoutineNoise(logging.Filter):
    """Drops what robosuite logs on every import and env (optional extras it did not find, the
    controller file it loaded); every other record passes."""

    _ROUTINE = (
        "private macro file",
        "setup_macros.py",
        "robosuite_models",
        "mink",
        "controller configuration",
    )

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not any(text in message for text in self._ROUTINE)


def image_key(camera: str) -> str:
    """robomimic's observation key of a camera: ``agentview`` -> ``agentview_image``."""
    return f"{camera}_image"


# -- controllers ------------------------------------------------------------------------------------


def controller_configs(robot: str, control_mode: str, control: str) -> dict:
    """robosuite 1.5's composite controller for ``robot`` with each arm driven by ``control_mode``
    (``OSC_POSE``, ``OSC_POSITION``, ...) taking ``absolute`` targets or ``delta`` changes.

    Both act in the world frame, as robosuite <= 1.4 (and so robomimic's datasets and Diffusion
    Policy's absolute-action conversion) did: absolute arm actions are [x, y, z, axis-angle (3)]
    of the end effector in world coordinates; the last dim is the gripper (-1 open, 1 closed).
    """
    # optional dependency: the simulator (robosuite extra)
    from robosuite.controllers import load_composite_controller_config

    if control not in ("absolute", "delta"):
        raise ValueError(f"control must be 'absolute' or 'delta', got {control!r}")
    cfg = load_composite_controller_config(robot=robot)
    arms = [
        name
        for name, part in cfg["body_parts"].items()
        if str(part.get("type", "")).startswith(("OSC", "IK"))
    ]
    if not arms:
        raise ValueError(
            f"robosuite's default controller for {robot!r} has no arm part to drive with {control_mode}"
        )
    for arm in arms:
        part = cfg["body_parts"][arm]
        part["type"] = control_mode
        part["input_type"] = control
        part["input_ref_frame"] = "world"
    return cfg


def _arm_parts(controller: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    if "body_parts" in controller:
        return [p for p in controller["body_parts"].values() if "input_type" in p or "control_delta" in p]
    return [controller]


def recorded_control(env_kwargs: Mapping[str, Any]) -> tuple[str | None, str | None]:
    """(controller type, ``absolute``/``delta``) of a robomimic file's ``env_kwargs``, in either
    robosuite's old (<= 1.4: ``type`` + ``control_delta``) or new (composite ``body_parts``) form."""
    cfg = env_kwargs.get("controller_configs")
    if isinstance(cfg, list):  # one per robot
        cfg = cfg[0] if cfg else None
    if not isinstance(cfg, Mapping):
        return None, None
    parts = _arm_parts(cfg)
    if not parts:
        return None, None
    part = parts[0]
    if "input_type" in part:
        control = "delta" if part["input_type"] == "delta" else "absolute"
    else:
        control = "delta" if part.get("control_delta", True) else "absolute"
    return part.get("type"), control


def _modern_controller(cfg: Mapping[str, Any], robot: str) -> dict:
    """A robosuite <= 1.4 part controller config as 1.5's composite one, keeping its meaning:
    ``control_delta=False`` becomes ``input_type="absolute"``, and targets stay in the world frame."""
    # optional dependency: the simulator (robosuite extra)
    from robosuite.controllers.composite.composite_controller_factory import (
        refactor_composite_controller_config,
    )

    if "body_parts" in cfg:
        return copy.deepcopy(dict(cfg))
    old = copy.deepcopy(dict(cfg))
    delta = bool(old.pop("control_delta", True))
    old.setdefault("input_type", "delta" if delta else "absolute")
    old.setdefault("input_ref_frame", "world")
    return refactor_composite_controller_config(old, robot, ["right"])


# -- env kwargs -------------------------------------------------------------------------------------


def _robots(task: TaskConfig) -> list[str]:
    robots = task.env.get("robots", ["Panda"])
    return [robots] if isinstance(robots, str) else list(robots)


def env_args_for_task(
    task: TaskConfig, *, cameras: Sequence[str] | None = None, render: bool = False
) -> dict:
    """robomimic's ``env_args`` (``env_name``, ``env_version``, ``type``, ``env_kwargs``) of a task:
    what :func:`make_from_env_args` makes, and what the demonstration files record.

    ``task.env`` may hold any ``robosuite.make`` keyword (``robots``, ``env_configuration``,
    ``control_freq``, ``hard_reset``, ...); ``cameras`` default to the task's.
    """
    robosuite = import_robosuite()
    cameras = list(task.cameras if cameras is None else cameras)
    robots = _robots(task)
    extra = {k: v for k, v in task.env.items() if k != "robots"}
    kwargs: dict[str, Any] = {
        "robots": robots,
        "controller_configs": controller_configs(robots[0], task.control_mode, task.control),
        "has_renderer": False,
        "has_offscreen_renderer": bool(cameras) or render,
        "ignore_done": True,
        "use_object_obs": True,
        "use_camera_obs": bool(cameras),
        "camera_names": cameras or ["agentview"],
        "camera_heights": task.image_size,
        "camera_widths": task.image_size,
        "camera_depths": False,
        "control_freq": 20,
        "reward_shaping": task.reward_mode == "dense",
        "hard_reset": False,  # resets in place, 0.4-1 s faster each; observations are the same
        # the scene's construction draws (Lift's cube size, ...) from a fixed seed, so that every
        # env instance (workers, evaluation, replay) builds the same scene and an episode seed
        # (seed_episode) alone decides an episode's initial state
        "seed": 0,
    }
    kwargs.update(extra)
    return {
        "env_name": task.env_id,
        "env_version": robosuite.__version__,
        "type": ROBOMIMIC_ENV_TYPE,
        "env_kwargs": kwargs,
    }


def make_from_env_args(
    env_args: Mapping[str, Any],
    *,
    cameras: Sequence[str] | None = None,
    image_size: int | None = None,
    render: bool = False,
    source: str = "env_args",
):
    """A robosuite env from robomimic ``env_args`` (ours, or a user's robomimic/MimicGen file's).

    ``cameras``/``image_size`` override the recorded cameras (``[]``: none, the fast path);
    robosuite <= 1.4 controller configs are translated to 1.5's composite form. ``source`` names
    the file in error messages.
    """
    suite = import_robosuite()
    name = env_args.get("env_name")
    if name not in suite.ALL_ENVIRONMENTS:
        hint = " (a MimicGen task: pip install mimicgen, which registers it)" if "_D" in str(name) else ""
        raise ValueError(
            f"{source}: env_name {name!r} is not a robosuite environment{hint}; known: "
            f"{sorted(suite.ALL_ENVIRONMENTS)}"
        )
    kwargs = copy.deepcopy(dict(env_args.get("env_kwargs", {})))
    kwargs.pop("env_name", None)
    robots = kwargs.get("robots", ["Panda"])
    robot = robots if isinstance(robots, str) else robots[0]
    if "controller_configs" in kwargs:
        kwargs["controller_configs"] = _modern_controller(kwargs["controller_configs"], robot)
    if cameras is not None:
        cams = list(cameras)
        kwargs["use_camera_obs"] = bool(cams)
        kwargs["camera_names"] = cams or ["agentview"]
    if image_size is not None:
        kwargs["camera_heights"] = kwargs["camera_widths"] = int(image_size)
    kwargs["has_renderer"] = False
    kwargs["has_offscreen_renderer"] = bool(kwargs.get("use_camera_obs")) or render
    kwargs["ignore_done"] = True
    try:
        env = suite.make(name, **kwargs)
    except TypeError as err:
        raise ValueError(
            f"{source}: robosuite.make({name!r}) refused the recorded env_kwargs: {err}"
        ) from err
    _fresh_kinematics(env)
    return env


# -- episodes ---------------------------------------------------------------------------------------


def seed_episode(env, seed: int | None) -> None:
    """Make the next ``env.reset()`` draw its initial state from ``seed``. robosuite's placement
    samplers and robot-noise draws hold a reference to ``env.rng``, so it is re-seeded in place."""
    if seed is not None:
        env.rng.bit_generator.state = np.random.default_rng(int(seed)).bit_generator.state


def step(env, action: np.ndarray) -> tuple[dict, float]:
    """``env.step(action)``: (raw obs, reward); the observation is a function of the new state (see
    :func:`_fresh_kinematics`)."""
    raw, reward, _, _ = env.step(np.asarray(action, dtype=np.float64))
    return raw, float(reward)


def _fresh_kinematics(env) -> None:
    """Make ``env``'s observations a function of its MuJoCo state.

    MuJoCo's step integrates positions after computing kinematics, so robosuite's post-step
    observation mixes new joint positions with the previous substep's body, site and camera poses
    (~0.5 mm apart). Recomputing kinematics (``mj_kinematics``, a few microseconds) before robosuite
    samples its sensors fixes that, so that observations regenerated from a file's stored states
    equal those an env produced; the dynamics are untouched (each step recomputes them anyway).
    """
    # optional dependency: the simulator (robosuite extra)
    import mujoco

    sample = env._update_observables

    def update_observables(force: bool = False) -> None:
        mujoco.mj_kinematics(env.sim.model._model, env.sim.data._data)
        sample(force=force)

    env._update_observables = update_observables


def restore_state(env, state: np.ndarray, model_xml: str | None = None) -> dict:
    """Put ``env`` in a stored flattened MuJoCo state ([time, qpos, qvel], robomimic's ``states``)
    and return the observation there. With ``model_xml`` (robomimic's ``model_file``) the scene is
    rebuilt from it first (objects of another size or colour than a fresh reset draws)."""
    if model_xml is not None:
        env.reset_from_xml_string(env.edit_model_xml(model_xml))
        env.sim.reset()
    state = np.asarray(state, dtype=np.float64)
    expected = 1 + env.sim.model.nq + env.sim.model.nv
    if state.shape != (expected,):
        raise ValueError(f"a state of this scene has {expected} values (time, qpos, qvel), got {state.shape}")
    env.sim.set_state_from_flattened(state)
    env.sim.forward()
    if hasattr(env, "update_state"):
        env.update_state()  # e.g. the nut tasks' site bookkeeping
    return _read_observations(env)


def _read_observations(env) -> dict:
    """``env._get_observations(force_update=True)`` that leaves robosuite's sampling clocks alone.

    A forced read advances every observable's clock by one substep, as a simulated substep does;
    after it, each later ``env.step`` samples its observation that many substeps before the step
    ends (a state the file does not store). ``env.reset()`` leaves the clocks so that each step
    samples at its last substep, and so does this read."""
    clocks = [(o, o._time_since_last_sample, o._sampled) for o in env._observables.values()]
    raw = env._get_observations(force_update=True)
    for observable, since, sampled in clocks:
        observable._time_since_last_sample, observable._sampled = since, sampled
    return raw


def observation_arrays(
    raw: Mapping[str, np.ndarray], state_keys: Sequence[str], cameras: Sequence[str]
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A robosuite observation dict as (state float32 [D] in ``state_keys`` order, robomimic keys
    of the images as uint8 [3, H, W] upright). robosuite renders OpenGL's bottom-up rows; robomimic
    (and so every robomimic/MimicGen dataset) flips them upright, and so do we."""
    columns = []
    for key in state_keys:
        name = _ROBOSUITE_KEY.get(key, key)
        if name not in raw:
            low_dim = sorted(k for k in raw if not k.endswith("_image"))
            raise KeyError(f"robosuite observation has no {key!r} (state_keys); it has {low_dim}")
        columns.append(np.asarray(raw[name], dtype=np.float32).reshape(-1))
    state = np.concatenate(columns) if columns else np.zeros(0, dtype=np.float32)
    images = {}
    for cam in cameras:
        key = image_key(cam)
        if key not in raw:
            raise KeyError(f"robosuite observation has no {key!r}; was the env made with camera {cam!r}?")
        images[key] = np.ascontiguousarray(np.asarray(raw[key])[::-1].transpose(2, 0, 1))
    return state, images


def robomimic_obs(raw: Mapping[str, np.ndarray], cameras: Sequence[str]) -> dict[str, np.ndarray]:
    """A step's observation as robomimic records it: ``object`` (robosuite's ``object-state``),
    every per-robot entry (``robot0_eef_pos``, ...; not the ``proprio-state`` concatenation) and the
    cameras' images upright, channels last."""
    out: dict[str, np.ndarray] = {}
    for cam in cameras:
        out[image_key(cam)] = np.ascontiguousarray(np.asarray(raw[image_key(cam)])[::-1])
    if "object-state" in raw:
        out["object"] = np.asarray(raw["object-state"], dtype=np.float64)
    for key, value in raw.items():
        if key.startswith("robot") and key not in out and not key.endswith(("proprio-state", "_image")):
            out[key] = np.asarray(value, dtype=np.float64)
    return out


def dumps_env_args(env_args: Mapping[str, Any]) -> str:
    return json.dumps(env_args, default=lambda x: x.tolist() if hasattr(x, "tolist") else str(x))
