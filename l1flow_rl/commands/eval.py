"""``l1flow-rl eval``: score a checkpoint on the test seeds of an evaluation protocol, optionally
under another sampler, and write eval.json."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from l1flow_rl.config.overrides import overrides_under
from l1flow_rl.evaluation.evaluator import evaluate, sampler_record
from l1flow_rl.evaluation.plan import resolve_plan, task_from
from l1flow_rl.evaluation.rescore import eval_sampler
from l1flow_rl.export.pretrained import CONFIG_FILE, load_pretrained_for_eval
from l1flow_rl.utils.device import resolve_device
from l1flow_rl.workspace.checkpoint import load_actor, load_checkpoint
from l1flow_rl.workspace.harness import finished_run
from l1flow_rl.workspace.provenance import run_provenance
from l1flow_rl.workspace.report import format_summary
from l1flow_rl.workspace.teacher import total_steps

__all__ = ["run_eval", "write_eval_json"]


def write_eval_json(path: Path, record: dict[str, Any]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=2))
    return path


def _headline_rows(result: dict[str, Any], headline: str) -> dict[str, Any]:
    names = [headline, *(k for k in ("success_once", "success_at_end", "return") if k != headline)]
    rows: dict[str, Any] = {}
    for name in names:
        low, high = result["ci95"].get(name, (None, None))
        ci = f"  [{low:.3f}, {high:.3f}]" if low is not None and high is not None else ""
        rows[name] = f"{result[name]:.4f}{ci}"
    for name in ("episode_length", "episodes", "errors", "nfe_per_chunk"):
        rows[name] = result[name]
    rows["latency_ms_median (per chunk)"] = result["latency_ms_median"]
    return rows


def _samplerless(actor: Any, result: dict[str, Any]) -> dict[str, Any]:
    return {
        "name": type(actor).__name__,
        "kwargs": {},
        "nfe": result.get("nfe_per_chunk"),
        "prediction": None,
    }


def run_eval(cfg: DictConfig) -> int:
    """``l1flow-rl eval checkpoint=PATH [policy.sampler=... policy.sampler_kwargs.k=v]
    [eval.protocol=NAME] [eval.episodes=N] run_dir=DIR``: writes DIR/eval.json (test seeds) and the
    config beside it; ``resume=auto`` skips a DIR holding this very evaluation (an ``eval -m`` grid
    relaunched)."""
    done = finished_run(cfg, marker="eval.json")
    if done is not None:
        print(
            f"l1flow-rl eval: {cfg.run_dir} holds this evaluation, finished ({done}); skipped (resume=auto)"
        )
        return 0
    if not cfg.checkpoint:
        print(
            "l1flow-rl eval: pass checkpoint=PATH (a .pt file, a run's checkpoints/ folder, or a pretrained "
            "folder written by l1flow-rl export)"
        )
        return 2
    given = sorted(overrides_under("network"))
    if given:
        raise ValueError(f"l1flow-rl eval takes the network from the checkpoint; {given} may not be given")
    device = resolve_device(cfg.device)
    ledger = None  # the training stages behind the weights (a pretrained folder does not keep them)
    if (Path(cfg.checkpoint) / CONFIG_FILE).is_file():  # a pretrained folder (l1flow_rl.export.pretrained)
        actor, train_cfg = load_pretrained_for_eval(cfg.checkpoint, map_location=device)
    else:
        actor, train_cfg = load_actor(cfg.checkpoint, use_ema=True, map_location=device)
        ledger = load_checkpoint(cfg.checkpoint, mmap=True).get("ledger")
    trained = sampler_record(actor)
    name, kwargs = eval_sampler(train_cfg.policy, cfg.policy)
    if (name, kwargs) != (train_cfg.policy.sampler, dict(train_cfg.policy.sampler_kwargs or {})):
        actor = actor.with_sampler(name, **kwargs)  # refuses a sampler for another prediction type
    # The checkpoint's task is the one the policy acts in; the command line's task config only
    # applies (e.g. a longer max_episode_steps) when it names the same task.
    same_task = cfg.task.name == train_cfg.task.name
    if not same_task:
        print(f"evaluating on the checkpoint's task {train_cfg.task.name!r}, not {cfg.task.name!r}")
    task = task_from(cfg.task if same_task else train_cfg.task)
    if (task.obs_mode, task.control_mode) != (train_cfg.task.obs_mode, train_cfg.task.control_mode):
        raise ValueError(
            f"task.obs_mode/control_mode {task.obs_mode}/{task.control_mode} differ from the checkpoint's "
            f"{train_cfg.task.obs_mode}/{train_cfg.task.control_mode}"
        )
    plan = resolve_plan(cfg, task, device)
    run_dir = Path(cfg.run_dir)
    obs_horizon = int(train_cfg.policy.obs_horizon)
    result = evaluate(
        actor,
        lambda: plan.make_env(obs_horizon),
        episodes=plan.episodes,
        seed=plan.seed,
        deterministic=plan.deterministic,
        episode_metrics=plan.episode_metrics,
        video_dir=run_dir / "videos" if plan.video_episodes > 0 else None,
        video_episodes=plan.video_episodes,
        video_fps=plan.video_fps,
    )
    record = {
        "checkpoint": str(cfg.checkpoint),
        "task": task.name,
        **plan.record("test", result),
        # an actor with no sampler (FQL's one-step actor) is named by its class, with its counted NFE
        "sampler": {**(sampler_record(actor) or _samplerless(actor, result)), "trained_with": trained},
        **result,
    }
    if ledger:
        record.update(ledger=ledger, total_steps_with_teacher=total_steps(ledger))
    record["provenance"] = run_provenance()
    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / "config.yaml")  # what resume=auto compares a relaunch with
    path = write_eval_json(run_dir / "eval.json", record)
    sampler = record["sampler"]
    print(
        f"{task.name}, {cfg.checkpoint}: protocol {plan.protocol.name!r}, test seeds from {plan.seed}, "
        f"sampler {sampler['name']} {sampler['kwargs']} ({sampler['nfe']} NFE)\n"
        f"{format_summary(_headline_rows(result, plan.headline))}\nwrote {path}"
    )
    return 0
