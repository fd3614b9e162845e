"""Evaluations of a training run: validation seeds while training (they choose the best checkpoint)
and separate test seeds at the end (the reported figures). One env, made once and reused; an
evaluation never touches the training RNG."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from l1flow_rl.evaluation import evaluate
from l1flow_rl.evaluation.plan import resolve_plan, task_from
from l1flow_rl.workspace.logging import log_evaluation

__all__ = ["SELECTION_RULES", "PeriodicEvaluator", "choose_evaluation", "rule_text"]

#: which validated model is chosen, the highest validation figure with, of equals, the
#: - ``"latest"``: latest (training: with a cosine LR and an EMA a later checkpoint is the better prior);
#: - ``"earliest"``: earliest;
#: - ``"start"``: earliest, but the first evaluation is a start (fine-tuning's BC policy) that a later
#:   model replaces only when it validates more than one standard error above it: a lead within the
#:   validation's noise is no evidence of a better policy (the measurement: docs/finetune.md).
SELECTION_RULES = ("earliest", "latest", "start")


def _binomial_standard_error(p: float, n: int) -> float:
    return math.sqrt(p * (1 - p) / n) if n and 0 <= p <= 1 else 0.0


def _result_standard_error(result: dict[str, Any], headline: str) -> float | None:
    """An evaluation's standard error of ``headline``: binomial for a rate, else the one its 95 %
    interval implies; None when it has neither."""
    if (result.get("ci_method") or {}).get(headline) == "wilson":
        return _binomial_standard_error(float(result[headline]), int(result.get("episodes") or 0))
    low_high = (result.get("ci95") or {}).get(headline)
    if low_high is None or None in low_high:
        return None
    return (low_high[1] - low_high[0]) / (2 * 1.959964)


def _standard_error(row: dict[str, Any], headline: str) -> float:
    """A validation row's standard error: recorded when it ran, else (a row without one) binomial."""
    if row.get("standard_error") is not None:
        return float(row["standard_error"])
    return _binomial_standard_error(float(row[headline]), int(row.get("episodes") or 0))


def rule_text(val: Sequence[dict[str, Any]], headline: str, rule: str) -> str:
    """How a selection under ``rule`` over the validation rows ``val`` describes itself."""
    ties = "latest" if rule == "latest" else "earliest"
    text = f"highest validation {headline}, the {ties} of equals"
    if rule == "start":
        margin = _standard_error(val[0], headline)
        text += f"; the start (the first) kept unless beaten by over {margin:.3f}, its standard error"
    return text


def choose_evaluation(val: Sequence[dict[str, Any]], headline: str, rule: str) -> dict[str, Any]:
    """The chosen one of the validation rows ``val`` (in order) under ``rule`` (:data:`SELECTION_RULES`)."""
    if rule not in SELECTION_RULES:
        raise ValueError(f"rule={rule!r}; expected one of {SELECTION_RULES}")
    if not val:
        raise ValueError("no validation evaluation to choose from")
    # max keeps the first of equal values: the reversed list gives the latest of them
    best = lambda rows: max(rows if rule != "latest" else rows[::-1], key=lambda e: e[headline])  # noqa: E731
    if rule != "start" or len(val) == 1:
        return best(list(val))
    start, later = val[0], best(list(val[1:]))
    return later if later[headline] > start[headline] + _standard_error(start, headline) else start


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
        row["standard_error"] = _result_standard_error(result, self.headline)  # the "start" rule's margin
        return row

    def selection(
        self, evals: Sequence[dict[str, Any]], final_step: int, rule: str = "earliest"
    ) -> dict[str, Any]:
        """Which model the test figures belong to: the validation evaluation that ``rule``
        (:data:`SELECTION_RULES`) chooses, or the final model when no validation ran."""
        if rule not in SELECTION_RULES:
            raise ValueError(f"rule={rule!r}; expected one of {SELECTION_RULES}")
        val = [e for e in evals if e.get("split", "val") == "val"]
        if not val:
            return {
                "split": None,
                "step": final_step,
                "rule": "final model: no validation during training (train.eval_every=0)",
            }
        best = choose_evaluation(val, self.headline, rule)
        return {
            "split": "val",
            "step": best["step"],
            "rule": rule_text(val, self.headline, rule),
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
