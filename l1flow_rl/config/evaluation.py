"""Evaluation settings (``eval``): protocol, validation and test seeds, envs, videos.

Checkpoints are chosen on the validation seeds (``val_seed``, ``val_episodes``); the reported
figures come from the test seeds (``seed``, ``episodes``), which the two ranges keep apart
(checked with the protocols, :func:`l1flow_rl.evaluation.plan.eval_config_problems`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from l1flow_rl.config.ranges import bounded

__all__ = ["EvalConfig"]


@dataclass
class EvalConfig:
    # How figures are measured (l1flow_rl.evaluation.protocol_names()): default | maniskill | ...
    protocol: str = "default"
    # false: train and finetune run without any evaluation: no validation, no test, no evaluator or
    # eval env made; checkpoints/latest.pt only (no best.pt, no eval.json). l1flow-rl eval refuses it.
    enabled: bool = True
    # test episodes: the reported figures
    episodes: int = bounded(100, ge=1)
    # test seeds: seed, seed + 1, ... (Diffusion Policy's convention)
    seed: int = bounded(100_000, ge=0, lt=2**32)
    # episodes of each validation (checkpoint choice)
    val_episodes: int = bounded(0, ge=0, zero="as many as eval.episodes")
    # validation seeds, disjoint from the test seeds and from demo seeds
    val_seed: int = bounded(10_000, ge=0, lt=2**32)
    # Validation under another sampler of the same network (None: policy.sampler), e.g. ddim with
    # {steps: 16} for a DDPM-100 run: its curve and checkpoint choice at a sixth of the cost; the
    # test figures keep policy.sampler.
    val_sampler: str | None = None
    val_sampler_kwargs: dict = field(default_factory=dict)
    num_envs: int = bounded(2, ge=1)
    # Where the simulator runs (None: the protocol's, else the run's device). "cpu" with device=cuda
    # trains and samples on the GPU while the envs step on their CPU backend (ManiSkill: physx_cpu
    # workers), e.g. where ManiSkill's physx_cuda is unavailable.
    env_device: str | None = None
    # Episodes filmed (mp4 in run_dir/videos, and to the logger); None: 1 on a GPU, 0 on the CPU,
    # where the first rendered frame costs seconds.
    video_episodes: int | None = bounded(None, ge=0, optional=True)
    video_fps: int = bounded(20, ge=1)
    deterministic: bool = False
