"""``l1flow-rl train``: demonstrations -> chunk replay buffer -> loss -> AdamW/cosine/EMA -> evaluation.

A plain TorchRL loop. Rank 0 owns demonstrations, evaluation, checkpoints and logs; under
``torchrun`` every rank trains on its own sample stream and DDP keeps the replicas in sync, and a
failure on one rank ends every rank with its error (:mod:`l1flow_rl.workspace.distributed`).
"""

from __future__ import annotations

import functools
import json
import os
import random
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from l1flow_rl.data import fit_normalizers
from l1flow_rl.evaluation.evaluator import sampler_record
from l1flow_rl.workspace.build import build_actor, build_loss
from l1flow_rl.workspace.checkpoint import (
    check_resumable,
    get_buffer_rng,
    get_rng_state,
    load_actor,
    load_checkpoint,
    save_checkpoint,
    set_buffer_rng,
    set_rng_state,
)
from l1flow_rl.workspace.dataset import load_task_episodes, make_train_buffer, resolve_dataset
from l1flow_rl.workspace.distributed import (
    init_distributed,
    resolve_device,
    run_on_every_rank,
    run_on_rank0,
)
from l1flow_rl.workspace.evaluator import PeriodicEvaluator
from l1flow_rl.workspace.logging import make_logger
from l1flow_rl.workspace.machine import machine_info
from l1flow_rl.workspace.report import format_summary, save_history, save_plots
from l1flow_rl.workspace.run_clock import RunClock
from l1flow_rl.workspace.trainer import Trainer

__all__ = ["resolve_device", "run_train"]


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _obs_shapes(episodes) -> dict[str, tuple[int, ...]]:
    obs = episodes["observation"]
    if isinstance(obs, torch.Tensor):
        return {"state": tuple(obs.shape[1:])}
    return {k: tuple(v.shape[1:]) for k, v in obs.items()}


def _device(cfg: DictConfig, world: int) -> torch.device:
    device = resolve_device(cfg.device)
    if device.type == "cuda" and world > 1:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0)))
        torch.cuda.set_device(device)
    return device


def _resume_state(cfg: DictConfig, latest: Path) -> dict[str, Any] | None:
    """The checkpoint to continue (``resume=true``), refused if the config changes what it trained."""
    if not cfg.resume:
        return None
    if not latest.is_file():
        raise FileNotFoundError(
            f"resume=true but {str(latest)!r} does not exist; pass the run's directory as run_dir=... "
            "(every run gets a new directory by default), or drop resume=true to start fresh"
        )
    state = load_checkpoint(latest)
    check_resumable(state["config"], cfg, str(latest))
    return state


def _rank0_due(cfg: DictConfig, step: int) -> bool:
    """Whether rank 0 logs, evaluates or checkpoints after ``step`` (every rank computes the same)."""
    t = cfg.train
    evaluates = cfg.eval.episodes > 0 and t.eval_every and step % t.eval_every == 0
    return bool(step % t.log_every == 0 or step % t.checkpoint_every == 0 or step == t.steps or evaluates)


def run_train(cfg: DictConfig) -> int:
    """Train ``cfg.policy`` on ``cfg.task``'s demonstrations; rank 0 evaluates and reports.

    Under torchrun, rank-0-only work (demonstrations, evaluation, checkpoints, the report) runs
    through :func:`run_on_rank0`, so its failure ends every rank with its error and its length
    never trips the process group's timeout.
    """
    rank, world = init_distributed()
    is_main = rank == 0
    device = _device(cfg, world)
    _seed_everything(cfg.seed + rank)
    run_dir, tcfg = Path(cfg.run_dir), cfg.train
    ckpt_dir = run_dir / "checkpoints"
    latest = ckpt_dir / "latest.pt"
    resume_state = run_on_every_rank(lambda: _resume_state(cfg, latest), "reading the checkpoint to resume")
    rank0: dict[str, Any] = {"evaluator": None, "logger": None}  # objects that live on rank 0 only

    def preflight() -> None:
        if resume_state is None and latest.is_file():
            raise FileExistsError(
                f"{str(run_dir)!r} already holds a run ({latest}); pass resume=true to continue it "
                "or choose another run_dir"
            )
        # Resolved before any demonstration is made: a bad protocol or overlapping seeds fail first.
        if cfg.eval.episodes > 0:
            rank0["evaluator"] = PeriodicEvaluator(cfg, device)

    run_on_rank0(preflight, "checking the run directory and the evaluation protocol")

    # -- data --------------------------------------------------------------------------------
    clock = RunClock(resume_state.get("elapsed") if resume_state else None, phases=("demo", "train"))
    clock.start("demo")
    dataset = run_on_rank0(lambda: resolve_dataset(cfg), "making or finding the demonstrations")
    clock.stop("demo")
    pcfg = cfg.policy

    def setup() -> tuple[Any, ...]:
        episodes = load_task_episodes(cfg, dataset)
        buffer = make_train_buffer(cfg, episodes, seed=cfg.seed + rank)
        action_dim = int(episodes["action"].shape[-1])
        obs_shapes = _obs_shapes(episodes)
        actor = build_actor(pcfg, obs_shapes, action_dim, cfg.get("encoder"))
        fit_normalizers(actor.policy, episodes, mode=pcfg.normalizer, obs_mode=pcfg.obs_normalizer)
        actor.to(device)
        return buffer, action_dim, obs_shapes, actor, build_loss(actor, pcfg)

    # -- model -------------------------------------------------------------------------------
    buffer, action_dim, obs_shapes, actor, loss_fn = run_on_every_rank(
        setup, "loading the demonstrations and building the model"
    )
    trainer = Trainer(
        actor,
        loss_fn,
        total_steps=tcfg.steps,
        lr=tcfg.lr,
        betas=tuple(tcfg.betas),
        weight_decay=tcfg.weight_decay,
        warmup_steps=tcfg.warmup_steps,
        ema_power=tcfg.ema_power,
        grad_clip=tcfg.grad_clip,
        amp=tcfg.amp,
        compile=tcfg.compile,
        check_values=False,  # the loader checked every value (data.episodes.check_finite)
    )
    history: dict[str, list[float]] = {"step": [], "loss": [], "lr": []}
    evals: list[dict[str, Any]] = []
    best = -1.0
    logger_state = None
    if resume_state is not None:
        trainer.load_state_dict(resume_state)
        clock.resumed_at(trainer.step)
        set_rng_state(resume_state["rng"])
        set_buffer_rng(buffer, resume_state["sampler_rng"])
        history, evals, best = resume_state["history"], resume_state["evals"], resume_state["best"]
        logger_state = resume_state.get("logger")

    def open_logger() -> None:
        run_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(cfg, run_dir / "config.yaml")
        rank0["logger"] = make_logger(
            tcfg.logger,
            run_dir,
            logger_state,
            project=tcfg.project,
            group=tcfg.group,
            run_name=tcfg.run_name,
            config=OmegaConf.to_container(cfg, resolve=True),
        )
        if rank0["evaluator"] is not None:
            rank0["evaluator"].logger = rank0["logger"]  # every metric of every evaluation, and its videos

    run_on_rank0(open_logger, "opening the run directory and the logger")
    evaluator, logger = rank0["evaluator"], rank0["logger"]

    def checkpoint_state() -> dict[str, Any]:
        state = trainer.state_dict()
        state.update(
            config=OmegaConf.to_container(cfg, resolve=True),
            obs_shapes={k: list(v) for k, v in obs_shapes.items()},
            action_dim=action_dim,
            dataset=str(dataset),
            rng=get_rng_state(),
            sampler_rng=get_buffer_rng(buffer),
            history=history,
            evals=evals,
            best=best,
            elapsed=clock.totals(),
            logger=logger.state_dict() if logger is not None and hasattr(logger, "state_dict") else None,
        )
        return state

    # -- loop --------------------------------------------------------------------------------
    from tqdm import tqdm

    t_train = time.perf_counter()
    clock.start("train")
    first_step = trainer.step
    bar = tqdm(total=tcfg.steps, initial=first_step, disable=not is_main, desc="train", dynamic_ncols=True)

    def after_step(step: int, step_metrics: dict[str, Any]) -> None:
        nonlocal best
        if step % tcfg.log_every == 0 or step == tcfg.steps:
            # The step's metrics stay on the device until here: reading them waits for it, so
            # they are read only on the steps that log.
            metrics = {k: float(v) for k, v in step_metrics.items()}
            rate = (step - first_step) / max(time.perf_counter() - t_train, 1e-9)
            bar.set_postfix(loss=f"{metrics['loss']:.4f}", lr=f"{metrics['lr']:.2e}", it_s=f"{rate:.1f}")
            history["step"].append(step)
            history["loss"].append(metrics["loss"])
            history["lr"].append(metrics["lr"])
            for k, v in metrics.items():
                logger.log_scalar(f"train/{k}", v, step=step)
        if evaluator is not None and tcfg.eval_every and step % tcfg.eval_every == 0 and step < tcfg.steps:
            result = evaluator(trainer.ema_actor, step, split="val")
            evals.append(evaluator.history_row(result))
            value = result[evaluator.headline]
            bar.write(
                f"step {step}: validation {evaluator.headline}={value:.3f} over {result['episodes']} episodes"
            )
            if value > best:
                best = value
                save_checkpoint(ckpt_dir / "best.pt", checkpoint_state())
        if step % tcfg.checkpoint_every == 0 or step == tcfg.steps:
            save_checkpoint(latest, checkpoint_state())

    try:
        while trainer.step < tcfg.steps:
            batch = buffer.sample().to(device)
            metrics = trainer.train_step(batch)
            step = trainer.step
            bar.update(1)
            if _rank0_due(cfg, step):
                run_on_rank0(
                    functools.partial(after_step, step, metrics),
                    f"logging/evaluating/checkpointing at step {step}",
                )
    finally:
        bar.close()
    clock.stop("train")

    # -- final evaluation and report ------------------------------------------------------
    def report() -> None:
        nonlocal best
        summary: dict[str, Any] = {
            "task": cfg.task.name,
            "policy": cfg.policy.name,
            "steps": trainer.step,
            "demos": cfg.demos.num,
        }
        # A run resumed after its final validation (killed during the test episodes) has it already.
        validated = any(e["step"] == trainer.step and e.get("split") == "val" for e in evals)
        if evaluator is not None:
            if evals and not validated:  # validation ran during training: the final model competes
                val = evaluator(trainer.ema_actor, trainer.step, split="val")
                evals.append(evaluator.history_row(val))
                if val[evaluator.headline] > best:
                    best = val[evaluator.headline]
                    save_checkpoint(ckpt_dir / "best.pt", checkpoint_state())
            else:  # the final model is the only candidate
                save_checkpoint(ckpt_dir / "best.pt", checkpoint_state())
            save_checkpoint(latest, checkpoint_state())
            # The reported figures: the chosen model on the test seeds, which chose nothing.
            selection = evaluator.selection(evals, trainer.step)
            chosen = trainer.ema_actor
            if selection["step"] != trainer.step:
                chosen = load_actor(ckpt_dir / "best.pt", use_ema=True, map_location=device)[0]
            result = evaluator(chosen, trainer.step, video_dir=run_dir / "videos", split="test")
            evaluator.close()
            evals.append(evaluator.history_row(result))
            result = {**result, "selection": selection, "sampler": sampler_record(chosen)}
            (run_dir / "eval.json").write_text(json.dumps(result, indent=2))
            summary.update(
                success_once=result["success_once"],
                success_at_end=result["success_at_end"],
                eval_episodes=result["episodes"],
                chunk_latency_ms_median=result.get("latency_ms_median"),
            )
        # Seconds over every invocation of the run; CPU is the budget when runs share the machine.
        summary.update(clock.summary())  # seconds_since_step 0: the figures cover the whole run
        summary["machine"] = machine_info(device)  # threads and load as this invocation ended
        save_plots(history, evals, run_dir)
        save_history(history, evals, run_dir)
        (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
        print(format_summary(summary))
        print(f"run directory: {run_dir}")

    run_on_rank0(report, "evaluating the final model and writing the report")
    return 0
