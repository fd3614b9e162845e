"""Evaluation settings (``eval``): protocol, validation and test seeds, envs, videos.

Checkpoints are chosen on the validation seeds (``val_seed``, ``val_episodes``); the reported
figures come from the test seeds (``seed``, ``episodes``), which the two ranges keep apart
(checked with the protocols, :func:`l1flow_rl.evaluation.plan.eval_config_problems`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

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
