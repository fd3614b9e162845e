"""``l1flow-rl train``: demonstrations -> chunk replay buffer -> loss -> AdamW/cosine/EMA -> evaluation.

A plain TorchRL loop on the run harness (:class:`~l1flow_rl.workspace.harness.Run`: run directory,
resume, checkpoints, validation, the report). Rank 0 owns demonstrations, evaluation, checkpoints
and logs; under ``torchrun`` every rank trains on its own sample stream and DDP keeps the replicas
in sync, and a failure on one rank ends every rank with its error
(:mod:`l1flow_rl.workspace.distributed`).
"""

from __future__ import annotations

import os
from typing import Any

import torch
from omegaconf import DictConfig

from l1flow_rl.data import fit_normalizers
from l1flow_rl.workspace.build import build_actor, build_loss
from l1flow_rl.workspace.checkpoint import get_buffer_rng, set_buffer_rng
from l1flow_rl.workspace.dataset import load_task_episodes, make_train_buffer, resolve_dataset
from l1flow_rl.workspace.distributed import init_distributed, resolve_device, run_on_every_rank, run_on_rank0
from l1flow_rl.workspace.harness import Run, finished_run
from l1flow_rl.workspace.teacher import load_teacher, own_stage, total_steps
from l1flow_rl.workspace.trainer import Trainer

__all__ = ["TRAIN_MAY_CHANGE", "resolve_device", "run_train"]

#: What a resumed ``train`` run may change beyond every job's list
#: (:data:`~l1flow_rl.workspace.checkpoint.RESUME_MAY_CHANGE`): its cadences and how fast it runs.
TRAIN_MAY_CHANGE: tuple[str, ...] = (
    "train.log_every",
    "train.checkpoint_every",
    "train.eval_every",
    "train.prefetch",  # sampling threads: speed only (resume is bit-exact only with 0)
    "train.compile",  # the same network, compiled or not
    "checkpoint",  # train reads no checkpoint= (eval and fine-tuning do)
)


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


def run_train(cfg: DictConfig) -> int:
    """Train ``cfg.policy`` on ``cfg.task``'s demonstrations; rank 0 evaluates and reports.
    ``resume=auto`` skips a run directory that holds this very run, finished (a grid relaunched)."""
    done = finished_run(cfg, may_differ=("checkpoint",))  # train reads no checkpoint=
    if done is not None:
        print(f"l1flow-rl train: {cfg.run_dir} holds this run, finished ({done.name}); skipped (resume=auto)")
        return 0
    rank, world = init_distributed()
    device, tcfg, pcfg = _device(cfg, world), cfg.train, cfg.policy
    harness = Run(
        cfg,
        job="train",
        device=device,
        may_change=TRAIN_MAY_CHANGE,
        phases=("demo", "train"),
        log_every=tcfg.log_every,
        checkpoint_every=tcfg.checkpoint_every,
        eval_every=tcfg.eval_every,
        # of equally validated checkpoints the latest: a short validation can tie an under-trained
        # early checkpoint with later ones that test far better, and ties are common at 20 episodes
        rule="latest",
    )
    with harness as run:
        with run.phase("demo"):
            dataset = run_on_rank0(lambda: resolve_dataset(cfg), "making or finding the demonstrations")

        # A distillation run's frozen teacher (the config check has vetted teacher=), and the stages
        # its weights went through: the run's ledger starts with them.
        teacher, ledger = (None, []) if not cfg.get("teacher") else load_teacher(cfg.teacher, device)

        def setup() -> tuple[Any, ...]:
            episodes = load_task_episodes(cfg, dataset)
            buffer = make_train_buffer(cfg, episodes, seed=cfg.seed + rank)
            action_dim = int(episodes["action"].shape[-1])
            obs_shapes = _obs_shapes(episodes)
            actor = build_actor(pcfg, obs_shapes, action_dim, cfg.get("encoder"), cfg.get("network"))
            fit_normalizers(actor.policy, episodes, mode=pcfg.normalizer, obs_mode=pcfg.obs_normalizer)
            actor.to(device)
            extra = {} if teacher is None else {"teacher": teacher}
            return (
                buffer,
                action_dim,
                obs_shapes,
                actor,
                build_loss(actor, pcfg, control=cfg.task.control, **extra),
            )

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

        def state() -> dict[str, Any]:
            return {
                **trainer.state_dict(),
                "obs_shapes": {k: list(v) for k, v in obs_shapes.items()},
                "action_dim": action_dim,
                "dataset": str(dataset),
                "sampler_rng": get_buffer_rng(buffer),
                "ledger": [*ledger, own_stage(pcfg.name, trainer.step, tcfg.batch_size)],
            }

        def load(saved: dict[str, Any]) -> None:
            trainer.load_state_dict(saved)
            set_buffer_rng(buffer, saved["sampler_rng"])

        run.begin(state, load, step=lambda: trainer.step, total=tcfg.steps)
        with run.phase("train"):
            while trainer.step < tcfg.steps:
                metrics = trainer.train_step(buffer.sample().to(device))
                run.step_done(trainer.step, metrics, trainer.ema_actor, last=trainer.step == tcfg.steps)
        summary = {"task": cfg.task.name, "policy": pcfg.name, "steps": trainer.step, "demos": cfg.demos.num}
        run.records["ledger"] = [*ledger, own_stage(pcfg.name, trainer.step, tcfg.batch_size)]  # history.json

        def tested_ledger(weights_step: int) -> dict[str, Any]:
            # the stages the tested weights went through: best.pt's, when validation chose an earlier step
            stages = [*ledger, own_stage(pcfg.name, weights_step, tcfg.batch_size)]
            return {"ledger": stages, "total_steps_with_teacher": total_steps(stages)}

        run.report_for_weights = tested_ledger
        if teacher is None:  # a plain run's ledger is its own steps: in the files, not worth a row
            run.report_unprinted.update(("ledger", "total_steps_with_teacher"))
        run.finish(trainer.ema_actor, summary)
    return 0
