"""Evaluations of a training run: validation seeds while training (they choose the best checkpoint)
and separate test seeds at the end (the reported figures). One env, made once and reused; an
evaluation never touches the training RNG."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from l1flow_rl.evaluation import evaluate
from l1flow_rl.evaluation.plan import resolve_plan, task_from
from l1flow_rl.workspace.logging import log_evaluation

__all__ = ["TIE_RULES", "PeriodicEvaluator"]

#: which of equally validated models is chosen: training keeps the latest (with a cosine LR and an
#: EMA a later checkpoint is the better prior), fine-tuning the earliest (its start wins ties)
TIE_RULES = ("earliest", "latest")


class PeriodicEvaluator:
    """Runs the protocol's evaluation of ``cfg`` on ``"val"`` or ``"test"`` seeds and sends every
    metric (and video) to ``logger`` under ``val/...`` or ``test/...``.

    Made before any demonstration is generated, so that a bad protocol or overlapping seed ranges
    fail first.
    """

    def __init__(self, cfg: DictConfig, device: torch.device, logger: Any = None) -> None:
        self.cfg, self.device, self.env, self.logger = cfg, device, None, logger
        self.plan = resolve_plan(cfg, task_from(cfg.task), device)

    @property
    def headline(self) -> str:
        """The metric that picks the best checkpoint (the protocol's headline)."""
        return self.plan.headline

    def __call__(self, actor, step: int, video_dir: Path | None = None, split: str = "val") -> dict[str, Any]:
        episodes, seed = self.plan.split(split)
        ev = self.cfg.eval
        if split == "val" and ev.get("val_sampler"):  # the same network under a cheaper sampler
            actor = actor.with_sampler(ev.val_sampler, **dict(ev.get("val_sampler_kwargs") or {}))
        if self.env is None:
            self.env = self.plan.make_env(self.cfg.policy.obs_horizon)
        filmed = self.plan.video_episodes if video_dir is not None else 0
        with torch.random.fork_rng(devices=[]), torch.no_grad():
            result = evaluate(
                actor,
                self.env,
                episodes=episodes,
                seed=seed,
                deterministic=self.plan.deterministic,
                episode_metrics=self.plan.episode_metrics,
                video_dir=video_dir if filmed else None,
                video_episodes=filmed,
                video_fps=self.plan.video_fps,
            )
        result = {**self.plan.record(split, result), **result, "step": step}
        if self.logger is not None:
            log_evaluation(self.logger, result, step, prefix=split)
        return result

    def history_row(self, result: dict[str, Any]) -> dict[str, Any]:
        """The few numbers of an evaluation that the run keeps (plots, checkpoint choice)."""
        keys = (
            "step",
            "split",
            "success_once",
            "success_at_end",
            "return",
            "episode_length",
            "episodes",
            "nfe_per_chunk",  # counted: shows which sampler scored it (eval.val_sampler)
        )
        row = {k: result[k] for k in keys if k in result}
        row[self.headline] = result[self.headline]
        return row

    def selection(
        self, evals: Sequence[dict[str, Any]], final_step: int, ties: str = "earliest"
    ) -> dict[str, Any]:
        """Which model the test figures belong to: the best validation evaluation (of equals, the
        ``ties`` one: ``"earliest"`` or ``"latest"``), or the final model when no validation ran."""
        if ties not in TIE_RULES:
            raise ValueError(f"ties={ties!r}; expected one of {TIE_RULES}")
        val = [e for e in evals if e.get("split", "val") == "val"]
        if not val:
            return {
                "split": None,
                "step": final_step,
                "rule": "final model: no validation during training (train.eval_every=0)",
            }
        # max keeps the first of equal values: the reversed list gives the latest of them
        best = max(val if ties == "earliest" else val[::-1], key=lambda e: e[self.headline])
        return {
            "split": "val",
            "step": best["step"],
            "rule": f"highest validation {self.headline}, the {ties} of equals",
            "sampler": self.cfg.eval.get("val_sampler") or self.cfg.policy.sampler,
            "value": best[self.headline],
            "seeds": {"first": self.plan.val_seed, "episodes": self.plan.val_episodes},
            "evaluations": [{"step": e["step"], self.headline: e[self.headline]} for e in val],
        }

    def close(self) -> None:
        # not ``env.is_closed``: TorchRL's envs report True until started, and a TransformedEnv
        # always; gated on it, the workers of ManiSkill's CPU envs ran until the interpreter exit
        if self.env is not None:
            self.env.close(raise_if_closed=False)
