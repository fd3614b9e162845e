"""Structured config schemas. Hydra merges YAML from ``configs/`` onto these, so a wrong key or a
value of the wrong type fails before any work starts, with the offending key in the message."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import OmegaConf

__all__ = [
    "CONFIG_DIR",
    "AppConfig",
    "DemosConfig",
    "EvalConfig",
    "PolicyConfig",
    "TaskConfig",
    "ToyConfig",
    "TrainConfig",
    "load_task_config",
    "task_names",
]

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
if not (CONFIG_DIR / "task").is_dir():  # installed (non-editable): configs ship as l1flow_rl.configs
    CONFIG_DIR = Path(__file__).resolve().parent / "configs"


@dataclass
class TaskConfig:
    """One simulator task: what to make, observe and control, and how long an episode may run."""

    name: str = "maniskill_pushcube"
    simulator: str = "maniskill"  # maniskill | robosuite | pusht
    env_id: str = "PushCube-v1"
    obs_mode: str = "state"  # state | rgb
    control_mode: str = "pd_ee_delta_pos"
    max_episode_steps: int = 100
    reward_mode: str = "normalized_dense"
    # Delta control pads chunks past an episode's end with zero arm motion (and the last gripper
    # command); absolute control repeats the last action.
    delta_control: bool = True
    image_size: int = 128
    env_kwargs: dict = field(default_factory=dict)


def task_names() -> list[str]:
    return sorted(p.stem for p in (CONFIG_DIR / "task").glob("*.yaml"))


def load_task_config(name: str, **overrides) -> TaskConfig:
    """Task config by name (a file in ``configs/task``), validated against :class:`TaskConfig`."""
    path = CONFIG_DIR / "task" / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"unknown task {name!r}; known tasks: {task_names()}")
    cfg = OmegaConf.merge(OmegaConf.structured(TaskConfig), OmegaConf.load(path), overrides)
    return OmegaConf.to_object(cfg)  # type: ignore[return-value]


@dataclass
class PolicyConfig:
    """Method and network. ``loss`` and ``sampler`` pick the method; the rest is the shared UNet."""

    name: str = "l1flow"
    loss: str = "l1flow"  # l1flow | flow_matching | diffusion | regression
    sampler: str = "two_step"  # two_step | euler | velocity_euler | ddpm | ddim | direct
    sampler_kwargs: dict = field(default_factory=dict)
    loss_kwargs: dict = field(default_factory=dict)
    obs_horizon: int = 2
    pred_horizon: int = 16
    action_steps: int = 8
    down_dims: list[int] = field(default_factory=lambda: [64, 128, 256])
    timestep_embed_dim: int = 64
    kernel_size: int = 5
    n_groups: int = 8
    normalizer: str = "limits"  # actions: limits | gaussian | identity
    # Observations: limits blows up near-constant state dims (a 0.003-wide range scaled to [-1, 1]),
    # so states pass through raw by default, as in ManiSkill's baseline.
    obs_normalizer: str = "identity"  # limits | gaussian | identity


@dataclass
class DemosConfig:
    """Demonstration generation (ManiSkill motion planning, then replay into obs/control mode)."""

    num: int = 100
    # Give up when this many planner attempts in a row fail (a task whose planner never succeeds).
    max_consecutive_failures: int = 50
    seed: int = 0


@dataclass
class TrainConfig:
    steps: int = 3000
    batch_size: int = 256
    lr: float = 1e-4
    betas: list[float] = field(default_factory=lambda: [0.95, 0.999])
    weight_decay: float = 1e-6
    warmup_steps: int = 500
    ema_power: float = 0.75
    grad_clip: float = 0.0  # 0 disables
    amp: bool = False
    compile: bool = False
    checkpoint_every: int = 1000
    log_every: int = 50
    eval_every: int = 0  # 0: evaluate only at the end
    logger: str = "csv"  # csv | tensorboard | wandb
    prefetch: int = 0  # batches sampled ahead by threads; 0 keeps resume bit-exact


@dataclass
class EvalConfig:
    episodes: int = 50
    num_envs: int = 2
    seed: int = 1000
    video_episodes: int = 0
    deterministic: bool = False


@dataclass
class ToyConfig:
    """The multi-modality demonstration (``l1flow-rl toy``); see :mod:`l1flow_rl.toy`."""

    steps: int = 600  # about 90 s of CPU time for the three methods (the toy runs single-threaded)
    batch_size: int = 128
    lr: float = 1e-3
    samples: int = 512
    seed: int = 0
    methods: list[str] = field(default_factory=lambda: ["l1flow", "flow_matching", "regression"])


@dataclass
class AppConfig:
    """The composed config of every ``l1flow-rl`` sub-command."""

    task: TaskConfig = field(default_factory=TaskConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    demos: DemosConfig = field(default_factory=DemosConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    toy: ToyConfig = field(default_factory=ToyConfig)
    data_dir: str = "data"
    run_dir: str = "runs/default"
    checkpoint: str | None = None
    resume: bool = False
    seed: int = 0
    device: str = "auto"  # auto | cpu | cuda
