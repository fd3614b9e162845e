"""``l1flow-rl finetune``: an L1 Flow BC checkpoint improved with rewards, offline then online.

    l1flow-rl finetune checkpoint=runs/bc/checkpoints/latest.pt task=maniskill_pushcube \\
        offline.steps=1000 online.steps=20000 eval.episodes=50 run_dir=runs/ft

1. Offline: ``offline.steps`` FlowQLoss updates on the BC run's demonstrations (their recorded
   rewards, cut into chunk windows with discounted chunk returns).
2. Online: rounds of ``online.frames_per_round`` environment steps collected by the fine-tuned
   policy (a TorchRL collector), each followed by ``updates_per_step`` updates per step, the
   demonstrations seeding (or sharing every batch with) the online data.
3. The final policy on the protocol's test seeds: ``RUN/eval.json``.

Checkpoints (``RUN/checkpoints/latest.pt``, and ``best.pt`` when validation runs) hold the
fine-tuned actor under ``"model"`` with a config that rebuilds it, so ``l1flow-rl eval`` takes them
unchanged; they also hold the critics, the optimiser, every RNG and (online) the replay buffer, and
``resume=true`` continues a run exactly. The run logs Q statistics, the BC loss, the distance to
the BC policy, and success against environment steps (``history.json``, ``finetune.png``).
"""

from __future__ import annotations

import json
import random
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from l1flow_rl.workspace.checkpoint import (
    CheckpointMismatchError,
    get_rng_state,
    load_actor,
    load_checkpoint,
    save_checkpoint,
    set_rng_state,
)
from l1flow_rl.workspace.collect import OnlineCollector, round_stats
from l1flow_rl.workspace.dataset import load_task_episodes, resolve_dataset
from l1flow_rl.workspace.distributed import resolve_device
from l1flow_rl.workspace.evaluator import PeriodicEvaluator
from l1flow_rl.workspace.flowq_trainer import FlowQTrainer, finetuned_policy_config
from l1flow_rl.workspace.logging import make_logger
from l1flow_rl.workspace.machine import machine_info
from l1flow_rl.workspace.rl_data import RLBuffers
from l1flow_rl.workspace.run_clock import RunClock

__all__ = ["run_finetune"]

# Config fields a resumed fine-tuning run may change (cadence, evaluation, where it runs); every
# other field of these groups, the task identity, the seed and the source checkpoint must match.
_MAY_CHANGE = {
    "finetune.log_every",
    "finetune.checkpoint_every",
    "offline.eval_every",
    "online.eval_every",
}
_MUST_MATCH_TOP = (
    "checkpoint",
    "seed",
    "task.env_id",
    "task.obs_mode",
    "task.control_mode",
    "task.reward_mode",
)


def _flat(node: Any, prefix: str) -> dict[str, Any]:
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for k, v in node.items():
            out.update(_flat(v, f"{prefix}.{k}"))
        return out
    return {prefix: node}


def _select(cfg: dict, dotted: str) -> Any:
    node: Any = cfg
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    return node


#: settings added after runs were made -> the value that behaves as runs made before them did (a
#: checkpoint without the field resumes under that value, and only under it)
_ADDED_LATER = {
    "finetune.reward": "recorded",
    "finetune.critic_input": "action",
    "finetune.critic_target": "td",
    "finetune.select_with": "critic",
}


def _check_resume(saved: dict, current: dict, path: Path) -> None:
    diffs = [
        f"{f}: checkpoint has {_select(saved, f)!r}, config asks for {_select(current, f)!r}"
        for f in _MUST_MATCH_TOP
        if _select(saved, f) != _select(current, f)
    ]
    for group in ("finetune", "offline", "online"):
        old, new = _flat(saved.get(group, {}), group), _flat(current.get(group, {}), group)
        old.update({k: v for k, v in _ADDED_LATER.items() if k.startswith(f"{group}.") and k not in old})
        diffs += [
            f"{k}: checkpoint has {old.get(k)!r}, config asks for {new.get(k)!r}"
            for k in sorted(set(old) | set(new))
            if k not in _MAY_CHANGE and old.get(k) != new.get(k)
        ]
    if diffs:
        raise CheckpointMismatchError(
            f"resume=true: {str(path)!r} was made with another config:\n  " + "\n  ".join(diffs)
        )


def _check_task(bc_cfg: DictConfig, cfg: DictConfig, path: str) -> None:
    fields = ("env_id", "obs_mode", "control_mode")
    diffs = [
        f"task.{f}: checkpoint has {bc_cfg.task.get(f)!r}, config asks for {cfg.task.get(f)!r}"
        for f in fields
        if bc_cfg.task.get(f) != cfg.task.get(f)
    ]
    if diffs:
        raise CheckpointMismatchError(
            f"checkpoint={path!r} was trained on another task than task={cfg.task.name!r}:\n  "
            + "\n  ".join(diffs)
        )


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _dataset(cfg: DictConfig, bc_state: dict) -> Path:
    """``data.path``, else the BC run's own demonstrations, else the task's expert demonstrations."""
    if cfg.data.path:
        return Path(cfg.data.path)
    saved = bc_state.get("dataset")
    if saved and Path(saved).exists():
        return Path(saved)
    return resolve_dataset(cfg)


def run_finetune(cfg: DictConfig) -> int:
    # optional dependency (app extra): the progress bar
    from tqdm import tqdm

    if not cfg.checkpoint:
        print("l1flow-rl finetune: pass checkpoint=PATH (the L1 Flow BC checkpoint to fine-tune)")
        return 2
    device = resolve_device(cfg.device)
    run_dir = Path(cfg.run_dir)
    ckpt_dir = run_dir / "checkpoints"
    latest = ckpt_dir / "latest.pt"

    # -- the BC policy and the run's config ----------------------------------------------------
    bc_state = load_checkpoint(cfg.checkpoint)
    bc_actor, bc_cfg = load_actor(cfg.checkpoint, use_ema=True, map_location=device)
    _check_task(bc_cfg, cfg, str(cfg.checkpoint))
    with open_dict(cfg):  # the network is the checkpoint's
        cfg.policy = OmegaConf.merge(cfg.policy, bc_cfg.policy)
        if bc_cfg.get("encoder") is not None and "encoder" in cfg:
            cfg.encoder = OmegaConf.merge(cfg.encoder, bc_cfg.encoder)
    plain = OmegaConf.to_container(cfg, resolve=True)
    fcfg = cfg.finetune
    best_of_n = {
        "num_samples": int(fcfg.num_samples),
        "rl_horizon": int(fcfg.rl_horizon) or int(cfg.policy.action_steps),
        "num_qvalue_nets": int(fcfg.num_qvalue_nets),
        "critic_hidden_dims": list(fcfg.critic_hidden_dims),
        "critic_input": str(fcfg.critic_input),
    }
    saved_cfg = {**plain, "policy": finetuned_policy_config(plain["policy"], fcfg.mode, best_of_n)}

    resume_state = None
    if cfg.resume:
        if not latest.is_file():
            raise FileNotFoundError(f"resume=true but {str(latest)!r} does not exist; drop resume=true")
        resume_state = load_checkpoint(latest)
        _check_resume(resume_state["finetune_config"], plain, latest)
    elif latest.is_file():
        raise FileExistsError(
            f"{str(run_dir)!r} already holds a run ({latest}); pass resume=true to continue it or choose "
            "another run_dir"
        )
    _seed_everything(cfg.seed)
    evaluator = PeriodicEvaluator(cfg, device) if cfg.eval.episodes > 0 else None

    # -- data and model -----------------------------------------------------------------------
    clock = RunClock(resume_state.get("elapsed") if resume_state else None, phases=("offline", "online"))
    dataset = _dataset(cfg, bc_state)
    episodes = load_task_episodes(cfg, dataset)
    trainer = FlowQTrainer(bc_actor, cfg.finetune)
    buffers = RLBuffers(cfg, episodes, trainer.rl_horizon, seed=cfg.seed)
    progress = {"offline_updates": 0, "online_round": 0, "env_steps": 0}
    history: dict[str, list] = {"updates": [], "env_steps": [], "phase": [], "metrics": []}
    evals: list[dict[str, Any]] = []
    rounds: list[dict[str, Any]] = []
    best, logger_state = -1.0, None
    if resume_state is not None:
        trainer.load_state_dict(resume_state["trainer"])
        clock.resumed_at(trainer.updates)
        if resume_state.get("online_buffer"):
            buffers.load_online(ckpt_dir / resume_state["online_buffer"])
        buffers.load_state_dict(resume_state["buffers"])
        set_rng_state(resume_state["rng"])
        progress, best = dict(resume_state["progress"]), float(resume_state["best"])
        history, evals, rounds = resume_state["history"], resume_state["evals"], resume_state["rounds"]
        logger_state = resume_state.get("logger")

    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / "config.yaml")
    logger = make_logger(cfg.train.logger, run_dir, logger_state, run_name="finetune")
    if evaluator is not None:
        evaluator.logger = logger
    obs_shapes = {k: list(v) for k, v in bc_state["obs_shapes"].items()}

    def checkpoint_state(online_buffer: str | None) -> dict[str, Any]:
        return {
            "model": trainer.policy_actor.state_dict(),
            "ema": None,
            "config": saved_cfg,
            "finetune_config": plain,
            "source_checkpoint": str(cfg.checkpoint),
            "obs_shapes": obs_shapes,
            "action_dim": int(bc_state["action_dim"]),
            "dataset": str(dataset),
            "trainer": trainer.state_dict(),
            "buffers": buffers.state_dict(),
            "online_buffer": online_buffer,
            "rng": get_rng_state(),
            "progress": dict(progress),
            "history": history,
            "evals": evals,
            "rounds": rounds,
            "best": best,
            "elapsed": clock.totals(),
            "logger": logger.state_dict() if hasattr(logger, "state_dict") else None,
        }

    buffer_dir: dict[str, str | None] = {"name": resume_state.get("online_buffer") if resume_state else None}

    def save(dump_online: bool) -> None:
        """latest.pt; with ``dump_online`` a fresh copy of the online buffer, which it names."""
        if dump_online:
            buffer_dir["name"] = f"online_buffer_round{progress['online_round']}"
            buffers.dump_online(ckpt_dir / buffer_dir["name"])
        save_checkpoint(latest, checkpoint_state(buffer_dir["name"]))
        for old in ckpt_dir.glob("online_buffer_round*"):  # latest.pt now names another one
            if old.name != buffer_dir["name"]:
                shutil.rmtree(old, ignore_errors=True)

    def log(metrics: dict[str, float], phase: str, batch) -> None:
        step = trainer.updates
        gen = torch.Generator().manual_seed(step)  # off the training RNG stream
        metrics = {
            **metrics,
            "bc_distance": trainer.bc_distance(batch, generator=gen),
            **trainer.critic_diagnostics(batch, generator=gen),
        }
        history["updates"].append(step)
        history["env_steps"].append(progress["env_steps"])
        history["phase"].append(phase)
        history["metrics"].append(metrics)
        for k, v in metrics.items():
            logger.log_scalar(f"{phase}/{k}", v, step=step)
        logger.log_scalar("env_steps", progress["env_steps"], step=step)

    def evaluate_now(phase: str) -> None:
        nonlocal best
        result = evaluator(trainer.policy_actor, trainer.updates, split="val")
        row = {**evaluator.history_row(result), "phase": phase, "env_steps": progress["env_steps"]}
        evals.append(row)
        logger.log_scalar("val/success_once_vs_env_steps", result["success_once"], step=progress["env_steps"])
        tqdm.write(
            f"[{phase}] update {trainer.updates}, env steps {progress['env_steps']}: validation "
            f"{evaluator.headline}={result[evaluator.headline]:.3f}"
        )
        if result[evaluator.headline] > best:
            best = result[evaluator.headline]
            save_checkpoint(ckpt_dir / "best.pt", checkpoint_state(None))

    # -- offline ------------------------------------------------------------------------------
    def postfix(bar, metrics: dict[str, float]) -> None:
        q = metrics.get("q_mean", metrics["q_data_mean"])  # critic warm-up: no actor chunks scored
        bar.set_postfix(q=f"{q:.2f}", qloss=f"{metrics['loss_qvalue']:.3f}", refresh=False)

    ocfg = cfg.offline
    critic_only = ocfg.critic_pretrain + ocfg.critic_warmup  # offline updates before the actor's first
    clock.start("offline")
    bar = tqdm(
        total=ocfg.steps, initial=progress["offline_updates"], desc="offline updates", dynamic_ncols=True
    )
    while progress["offline_updates"] < ocfg.steps:
        batch = buffers.sample_offline().to(device)
        done_before = progress["offline_updates"]
        if done_before < ocfg.critic_pretrain:
            metrics = trainer.update(batch, actor=False, critic="mc")
            # TD bootstraps from the target critics: they start from the fitted ones. Without TD they
            # only select (select_with=target), and keep their average
            if done_before + 1 == ocfg.critic_pretrain and fcfg.critic_target == "td":
                trainer.sync_target_critics()
        else:
            metrics = trainer.update(batch, actor=done_before >= critic_only, critic=fcfg.critic_target)
        progress["offline_updates"] += 1
        bar.update(1)
        done = progress["offline_updates"] == ocfg.steps
        if trainer.updates % fcfg.log_every == 0 or done:
            log(metrics, "offline", batch)
            postfix(bar, metrics)
        if (
            evaluator is not None
            and ocfg.eval_every
            and progress["offline_updates"] % ocfg.eval_every == 0
            # the acting policy changes with the actor, or with the critics where they select
            and (progress["offline_updates"] > critic_only or trainer.critics_act)
        ):
            evaluate_now("offline")
        if progress["offline_updates"] % fcfg.checkpoint_every == 0 or done:
            save(dump_online=False)
    bar.close()
    clock.stop("offline")

    # -- online -------------------------------------------------------------------------------
    on = cfg.online
    clock.start("online")
    if progress["env_steps"] < on.steps:
        bar = tqdm(total=on.steps, initial=progress["env_steps"], desc="online env steps", dynamic_ncols=True)
        with OnlineCollector(cfg, trainer.policy_actor, device) as collector:
            since_checkpoint, since_eval = 0, progress["env_steps"] % (on.eval_every or 1)
            while progress["env_steps"] < on.steps:
                data = collector.collect(progress["online_round"])
                stored = buffers.add_collected(data)
                frames = int(data.numel())
                progress["env_steps"] += frames
                progress["online_round"] += 1
                stats = {**round_stats(data), "steps_stored": stored, "env_steps": progress["env_steps"]}
                rounds.append(stats)
                for k, v in stats.items():
                    if v is not None:
                        logger.log_scalar(f"collect/{k}", v, step=progress["env_steps"])
                updates = round(on.updates_per_step * frames)
                for i in range(updates):
                    batch = buffers.sample_online().to(device)
                    metrics = trainer.update(batch, critic=fcfg.critic_target)
                    if trainer.updates % fcfg.log_every == 0 or i == updates - 1:
                        log(metrics, "online", batch)
                        postfix(bar, metrics)
                bar.update(frames)
                since_checkpoint += updates
                since_eval += frames
                last = progress["env_steps"] >= on.steps
                if evaluator is not None and on.eval_every and since_eval >= on.eval_every and not last:
                    since_eval = 0
                    evaluate_now("online")
                if since_checkpoint >= fcfg.checkpoint_every or last:
                    since_checkpoint = 0
                    save(dump_online=True)
        bar.close()
    clock.stop("online")

    # -- final evaluation and report -----------------------------------------------------------
    summary: dict[str, Any] = {
        "task": cfg.task.name,
        "mode": fcfg.mode,
        "source_checkpoint": str(cfg.checkpoint),
        "offline_updates": progress["offline_updates"],
        "env_steps": progress["env_steps"],
        "updates": trainer.updates,
    }
    if evaluator is not None:
        result = evaluator(trainer.policy_actor, trainer.updates, video_dir=run_dir / "videos", split="test")
        evaluator.close()
        evals.append({**evaluator.history_row(result), "phase": "final", "env_steps": progress["env_steps"]})
        result = {
            **result,
            "model": "final fine-tuned policy",
            "mode": fcfg.mode,
            "env_steps": progress["env_steps"],
            "updates": trainer.updates,
        }
        (run_dir / "eval.json").write_text(json.dumps(result, indent=2))
        summary.update(success_once=result["success_once"], eval_episodes=result["episodes"])
        if not (ckpt_dir / "best.pt").is_file():
            save_checkpoint(ckpt_dir / "best.pt", checkpoint_state(None))
    save(dump_online=False)  # the final state (history, evaluations); the buffer copy stays
    summary.update(clock.summary())  # offline/online/wall/cpu seconds over every invocation of the run
    summary["machine"] = machine_info(device)  # threads and load as this invocation ended
    (run_dir / "history.json").write_text(json.dumps({"history": history, "evals": evals, "rounds": rounds}))
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    _plot(history, evals, rounds, run_dir)
    print(json.dumps(summary, indent=2))
    print(f"run directory: {run_dir}")
    return 0


def _plot(history: dict, evals: list, rounds: list, run_dir: Path) -> None:
    """``finetune.png``: Q statistics and BC distance against updates, success against env steps."""
    # optional dependency (app extra): plots
    import matplotlib

    matplotlib.use("Agg")
    # optional dependency (app extra): plots
    import matplotlib.pyplot as plt

    fig, (ax_q, ax_s) = plt.subplots(1, 2, figsize=(11, 3.8))
    steps = history["updates"]
    for key in ("q_mean", "target_mean"):
        ax_q.plot(steps, [m.get(key, float("nan")) for m in history["metrics"]], lw=1, label=key)
    ax_q.set_xlabel("update")
    ax_q.set_ylabel("Q")
    ax_b = ax_q.twinx()
    ax_b.plot(steps, [m.get("bc_distance", float("nan")) for m in history["metrics"]], "k:", lw=1)
    ax_b.set_ylabel("distance to the BC policy (dotted)")
    ax_q.legend(loc="upper left")
    ax_q.grid(alpha=0.3)
    if evals:
        ax_s.plot(
            [e["env_steps"] for e in evals], [e["success_once"] for e in evals], "o-", label="evaluation"
        )
    if rounds:
        ax_s.plot(
            [r["env_steps"] for r in rounds],
            [float("nan") if r.get("episode_success") is None else r["episode_success"] for r in rounds],
            ".--",
            alpha=0.6,
            label="collected episodes",
        )
    ax_s.set_xlabel("environment steps")
    ax_s.set_ylabel("success rate")
    ax_s.set_ylim(-0.05, 1.05)
    ax_s.grid(alpha=0.3)
    if evals or rounds:
        ax_s.legend()
    fig.tight_layout()
    fig.savefig(run_dir / "finetune.png", dpi=110)
    plt.close(fig)
