"""Evaluation settings (``eval``): protocol, validation and test seeds, envs, videos.

Checkpoints are chosen on the validation seeds (``val_seed``, ``val_episodes``); the reported
figures come from the test seeds (``seed``, ``episodes``), which the two ranges keep apart.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from omegaconf import DictConfig

__all__ = ["EvalConfig"]


@dataclass
class EvalConfig:
    # How figures are measured (l1flow_rl.evaluation.protocol_names()): default | maniskill | ...
    protocol: str = "default"
    episodes: int = 50  # test episodes: the reported figures
    seed: int = 100_000  # test seeds: seed, seed + 1, ... (Diffusion Policy's convention)
    val_episodes: int = 0  # episodes of each validation (checkpoint choice); 0: as many as the test
    val_seed: int = 10_000  # validation seeds, disjoint from the test seeds and from demo seeds
    # Validation under another sampler of the same network (None: policy.sampler), e.g. ddim with
    # {steps: 16} for a DDPM-100 run: its curve and checkpoint choice at a sixth of the cost; the
    # test figures keep policy.sampler.
    val_sampler: str | None = None
    val_sampler_kwargs: dict = field(default_factory=dict)
    num_envs: int = 2
    # Where the simulator runs (None: the protocol's, else the run's device). "cpu" with device=cuda
    # trains and samples on the GPU while the envs step on their CPU backend (ManiSkill: physx_cpu
    # workers), e.g. where ManiSkill's physx_cuda is unavailable.
    env_device: str | None = None
    # Episodes filmed (mp4 in run_dir/videos, and to the logger); None: 1 on a GPU, 0 on the CPU,
    # where the first rendered frame costs seconds.
    video_episodes: int | None = None
    video_fps: int = 20
    deterministic: bool = False


def _protocols() -> list[str]:
    from l1flow_rl.evaluation.protocols import protocol_names

    return protocol_names()


def _check_seeds(cfg: DictConfig, command: str) -> list[str]:
    ev = cfg.get("eval") if isinstance(cfg, DictConfig) else None
    if ev is None:
        return []
    from l1flow_rl.evaluation.plan import check_seed_ranges

    problems = []
    if ev.episodes < 1 and command == "eval":
        problems.append(f"eval.episodes={ev.episodes}: expected >= 1")
    if ev.val_episodes < 0:
        problems.append(f"eval.val_episodes={ev.val_episodes}: expected >= 0 (0: as many as eval.episodes)")
    try:
        check_seed_ranges(ev.val_seed, ev.val_episodes or ev.episodes, ev.seed, ev.episodes)
    except ValueError as err:
        problems.append(str(err))
    return problems


def _check_val_sampler(cfg: DictConfig, command: str) -> list[str]:
    """``eval.val_sampler``'s arguments, and that it reads what ``policy.loss`` trains (its name is a
    registered choice); the policy's own sampler check, under the eval field names."""
    ev = cfg.get("eval") if isinstance(cfg, DictConfig) else None
    if ev is None or not ev.get("val_sampler") or cfg.get("policy") is None:
        return []
    from l1flow_rl.config.validate import check_policy
    from l1flow_rl.flow.samplers import sampler_names

    if ev.val_sampler not in sampler_names():  # reported by the choices check
        return []
    method = {
        "sampler": ev.val_sampler,
        "sampler_kwargs": ev.get("val_sampler_kwargs"),
        "loss": cfg.policy.loss,
    }
    return check_policy(method, sampler_field="eval.val_sampler")


def _samplers() -> list[str]:
    from l1flow_rl.flow.samplers import sampler_names

    return sampler_names()


def _register_checks() -> None:
    from l1flow_rl.config.validate import register_check, register_choices

    register_choices("eval.protocol", _protocols)
    register_choices("eval.val_sampler", _samplers)
    register_check(_check_seeds)
    register_check(_check_val_sampler)


_register_checks()
