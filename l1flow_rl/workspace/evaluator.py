"""Evaluation during and after training: one env, made once, reused; never touches the training RNG."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

__all__ = ["PeriodicEvaluator"]


class PeriodicEvaluator:
    """Creates the evaluation env once and reuses it; evaluation never touches the training RNG."""

    def __init__(self, cfg: DictConfig, device: torch.device) -> None:
        self.cfg, self.device, self.env = cfg, device, None

    def __call__(self, actor, step: int, video_dir: Path | None = None) -> dict[str, Any]:
        from l1flow_rl.envs import make_env
        from l1flow_rl.evaluation import evaluate

        if self.env is None:
            task = OmegaConf.to_object(self.cfg.task)
            self.env = make_env(
                task,
                num_envs=self.cfg.eval.num_envs,
                device=str(self.device),
                obs_horizon=self.cfg.policy.obs_horizon,
            )
        with torch.random.fork_rng(devices=[]), torch.no_grad():
            metrics = evaluate(
                actor,
                self.env,
                episodes=self.cfg.eval.episodes,
                seed=self.cfg.eval.seed,
                deterministic=self.cfg.eval.deterministic,
                video_dir=video_dir,
                video_episodes=self.cfg.eval.video_episodes if video_dir is not None else 0,
            )
        metrics["step"] = step
        return metrics

    def close(self) -> None:
        if self.env is not None and not self.env.is_closed:
            self.env.close()
