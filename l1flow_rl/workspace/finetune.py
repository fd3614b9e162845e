"""``l1flow-rl finetune finetune=qc|fql|dsrl checkpoint=BC.pt``: a BC policy improved with rewards.

    l1flow-rl finetune finetune=qc checkpoint=runs/bc/checkpoints/best.pt task=maniskill_pickcube \\
        online.steps=100000 eval.episodes=100 online.eval_every=10000

1. The BC start is validated first: it competes for ``best.pt``, so a run never reports a policy
   below its start.
2. Offline (``offline.steps``): updates on the demonstrations' chunk windows (QC, FQL).
3. Online: rounds of ``online.frames_per_round`` env steps from ``online.num_envs`` worker envs (a
   TorchRL collector); the first ``online.warmup_steps`` are the BC start's, then each round is
   followed by ``online.updates_per_step`` updates per env step past the warm-up, on batches that
   take ``online.offline_fraction`` of their windows from the demonstrations (TorchRL's
   ``OfflineToOnlineReplayBuffer``). Each round logs env steps/s, updates/s, the critic
   diagnostics and the collected episodes' success; validation every ``online.eval_every`` env steps.
4. The chosen policy (best validation, the start included) on the test seeds: ``eval.json``.

The run directory, resume (``resume=true``, exact: the online buffer and every RNG are in the
checkpoint; a finished run resumed with more ``online.steps`` goes on as the longer run would have),
checkpoints, validation and the report are the harness's
(:mod:`l1flow_rl.workspace.harness`); this module is the loop. Checkpoints hold the acting module
with a config that rebuilds it (``policy.finetune``), so ``l1flow-rl eval`` takes them unchanged.
"""

from __future__ import annotations

import copy
import shutil
import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.objectives import SoftUpdate
from tqdm import tqdm

from l1flow_rl.config.overrides import overrides_under
from l1flow_rl.modules.ema import DPEma, make_ema
from l1flow_rl.objectives.finetune_registry import FINETUNE_ALGORITHMS
from l1flow_rl.workspace.checkpoint import (
    CheckpointMismatchError,
    ResumeMismatchError,
    load_actor,
    load_checkpoint,
)
from l1flow_rl.workspace.collect import OnlineCollector, round_stats
from l1flow_rl.workspace.dataset import load_task_episodes, resolve_dataset
from l1flow_rl.workspace.distributed import resolve_device
from l1flow_rl.workspace.harness import Run
from l1flow_rl.workspace.rl_data import RLBuffers

__all__ = ["adopt_start_data", "check_extension", "run_finetune", "start_dataset"]

#: fields a resumed run may change beside the harness's: the cadences, and the two phases' lengths
#: (only to extend the run: :func:`check_extension`)
MAY_CHANGE = (
    "finetune.log_every",
    "offline.eval_every",
    "offline.checkpoint_every",
    "online.eval_every",
    "online.checkpoint_every",
    "offline.steps",
    "online.steps",
)


class ActingSwitch(TensorDictModuleBase):
    """The collector's policy: the BC start until ``trained`` is set, then the algorithm's actor
    (both write the same keys; the collector keeps one policy object for the whole run)."""

    def __init__(self, start: TensorDictModuleBase, actor: TensorDictModuleBase) -> None:
        super().__init__()
        if list(start.out_keys) != list(actor.out_keys):
            raise ValueError(f"the start writes {start.out_keys}, the actor {actor.out_keys}")
        self.start, self.actor, self.trained = start, actor, False
        self.in_keys, self.out_keys = list(actor.in_keys), list(actor.out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return (self.actor if self.trained else self.start)(tensordict)


def update(
    loss,
    optimizer: torch.optim.Optimizer,
    target_update,
    batch: TensorDictBase,
    ema: DPEma | None = None,
    averaged: torch.nn.Module | None = None,
) -> dict[str, Any]:
    """One update: every ``loss_*`` term summed, one Adam step, one Polyak step of the target critics,
    one step of the EMA (``finetune.ema_power``) of ``averaged`` (default: the loss's acting actor).
    Returns the loss's outputs (tensors: read to the host only when logged)."""
    out = loss(batch)
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    optimizer.step()
    if target_update is not None:
        target_update.step()
    if ema is not None:
        ema.update_parameters(loss.actor if averaged is None else averaged)
    return {k: v.detach() for k, v in out.items()}


def _crossed(every: int, before: int, now: int) -> bool:
    """A multiple of ``every`` lies in (before, now]."""
    return every > 0 and now // every > before // every


def _check_task(bc_cfg: DictConfig, cfg: DictConfig, path: str) -> None:
    diffs = [
        f"task.{f}: checkpoint has {bc_cfg.task.get(f)!r}, config asks for {cfg.task.get(f)!r}"
        for f in ("env_id", "obs_mode", "control_mode")
        if bc_cfg.task.get(f) != cfg.task.get(f)
    ]
    if diffs:
        raise CheckpointMismatchError(
            f"checkpoint={path!r} was trained on another task than task={cfg.task.name!r}:\n  "
            + "\n  ".join(diffs)
        )
    if bc_cfg.policy.get("finetune"):
        raise CheckpointMismatchError(
            f"checkpoint={path!r} is a fine-tuned policy ({bc_cfg.policy.finetune.algorithm}); pass the BC "
            "checkpoint it started from"
        )


def check_extension(progress: dict[str, Any], cfg: DictConfig, path: str) -> None:
    """A resumed run may be given more steps than it was started with (``online.steps=100000`` on a
    finished 60k run goes on from 60k, as the 100k run would have), never fewer than it has done;
    ``offline.steps`` may grow only while no env step has been taken (the offline phase comes first)."""
    done_off, done_on = int(progress["offline_updates"]), int(progress["env_steps"])
    errors = []
    if int(cfg.online.steps) < done_on:
        errors.append(f"online.steps={cfg.online.steps}: the run has already taken {done_on} env steps")
    if int(cfg.offline.steps) < done_off:
        errors.append(f"offline.steps={cfg.offline.steps}: the run already made {done_off} offline updates")
    elif int(cfg.offline.steps) > done_off and done_on > 0:
        errors.append(
            f"offline.steps={cfg.offline.steps}: the run made {done_off} offline updates and went online "
            f"({done_on} env steps); the offline phase can grow only before the first env step"
        )
    if errors:
        raise ResumeMismatchError(
            f"resume=true from {path!r}: a resume may lengthen a run, not shorten or reorder it:\n  "
            + "\n  ".join(errors)
        )


def adopt_start_data(cfg: DictConfig, bc_cfg: DictConfig, given: list[str]) -> None:
    """Fine-tune on the data the start was trained on: each ``demos.*`` and ``data.*`` field takes the
    BC run's value unless the command line sets it (``given``: the dotted keys it sets, e.g.
    ``["demos.num"]``, or ``["demos"]`` for a group choice), so ``config.yaml`` records the data the
    run trains on (it showed the defaults, 100 expert demonstrations, for a start trained on 30 mixed
    ones)."""
    with open_dict(cfg):
        for group in ("demos", "data"):
            if bc_cfg.get(group) is None or group in given:
                continue
            for key, value in bc_cfg[group].items():
                if f"{group}.{key}" not in given:
                    cfg[group][key] = value


def start_dataset(cfg: DictConfig, bc_state: dict, given: list[str]) -> Path:
    """The file the command line names (``data.path``) or makes (``demos.*``), else the BC run's own
    demonstrations, else the BC run's recipe (its ``demos``/``data``, adopted by
    :func:`adopt_start_data`) made again or found in ``data_dir``."""
    if any(k == "data.path" or k == "demos" or k.startswith("demos.") for k in given):
        return resolve_dataset(cfg)
    saved = bc_state.get("dataset")
    if saved and Path(saved).exists():
        return Path(saved)
    return resolve_dataset(cfg)


def run_finetune(cfg: DictConfig) -> int:
    if not cfg.checkpoint:
        print("l1flow-rl finetune: pass checkpoint=PATH (the L1 Flow BC checkpoint to fine-tune)")
        return 2
    device = resolve_device(cfg.device)
    bc_state = load_checkpoint(cfg.checkpoint)
    bc_actor, bc_cfg = load_actor(cfg.checkpoint, use_ema=True, map_location=device)
    _check_task(bc_cfg, cfg, str(cfg.checkpoint))
    with open_dict(cfg):  # the network is the checkpoint's
        cfg.policy = OmegaConf.merge(cfg.policy, bc_cfg.policy)
        if bc_cfg.get("network") is not None:
            cfg.network = OmegaConf.merge(cfg.network, bc_cfg.network)
        if bc_cfg.get("encoder") is not None and "encoder" in cfg:
            cfg.encoder = OmegaConf.merge(cfg.encoder, bc_cfg.encoder)
    given_data = [*overrides_under("demos"), *overrides_under("data")]
    adopt_start_data(cfg, bc_cfg, given_data)
    algorithm = FINETUNE_ALGORITHMS[cfg.finetune.algorithm]
    fcfg, off, on = cfg.finetune, cfg.offline, cfg.online
    plain = OmegaConf.to_container(cfg, resolve=True)
    # what rebuilds each acting module (load_actor): the BC policy's config, plus the algorithm's block
    start_config = {**plain, "policy": plain["policy"]}
    tuned_config = {**plain, "policy": {**plain["policy"], "finetune": plain["finetune"]}}

    with Run(
        cfg,
        job="finetune",
        device=device,
        may_change=MAY_CHANGE,
        phases=("offline", "online"),
        log_every=0,  # logged per offline log_every updates and per online round, below
        checkpoint_every=0,  # checkpointed below: an online checkpoint also dumps the buffer
        eval_every=0,
        history_keys=("loss_qvalue", "q_data_mean", "target_mean", "td_error_abs", "env_steps"),
        ties="earliest",  # the start is validated first: no reported policy falls below it
    ) as run:
        if run.resumed is not None:  # before the data and the networks are built
            check_extension(run.resumed["progress"], cfg, str(run.latest))
        dataset = start_dataset(cfg, bc_state, given_data)
        episodes = load_task_episodes(cfg, dataset)
        flow = copy.deepcopy(bc_actor)
        loss = algorithm.build(flow, fcfg).to(device)
        if getattr(loss, "proposal_cache", None) is not None:  # each seed draws its own cached proposals
            loss.proposal_cache.seed = int(cfg.seed)
        start = algorithm.start_actor(loss)
        # With finetune.ema_power the averaged actor acts, is validated, tested and saved (the raw one
        # trains): measured on Square, constant-LR iterates of continued BC swung 0.16-0.68 in 8k updates
        # Where the acting module wraps the trained BC flow (filtered BC: is it; QC: proposes with it),
        # the EMA averages that flow, whose weights are the BC run's EMA: the average goes on from the
        # BC run's counter, as if BC had gone on. From 0 it copied the first, shocked iterates (held L1
        # Flow loss 0.022 -> 0.055 in 10 updates at 3e-4; continued: 0.022-0.023;
        # benchmarks/results/finetune_shock_*.json). Otherwise (new networks act: a noise or one-step
        # actor; a frozen flow) the EMA averages the acting module from 0.
        flow_trains = any(p.requires_grad for p in flow.parameters())
        averaged = flow if algorithm.with_flow is not None and flow_trains else loss.actor
        ema = make_ema(averaged, power=float(fcfg.ema_power)) if fcfg.ema_power > 0 else None
        if ema is not None and averaged is flow and bc_state.get("ema_n_averaged") is not None:
            ema.n_averaged.copy_(bc_state["ema_n_averaged"])
        if ema is None:
            policy = loss.actor
        else:
            policy = algorithm.with_flow(loss, ema.module) if averaged is flow else ema.module
        acting = ActingSwitch(start, policy)
        optimizer = torch.optim.Adam([p for p in loss.parameters() if p.requires_grad], lr=float(fcfg.lr))
        # a loss without critics (filtered BC) has no targets to move
        has_targets = hasattr(loss, "target_qvalue_network_params")
        target_update = SoftUpdate(loss, tau=float(fcfg.tau)) if has_targets else None
        buffers = RLBuffers(
            cfg,
            episodes,
            loss.rl_horizon,
            seed=int(cfg.seed),
            online_keys=algorithm.online_keys,
            online_anchor_key=algorithm.online_anchor_key,
            successful_episodes_only=algorithm.successful_episodes_only,
        )
        kept, given = buffers.demo_episodes["kept"], buffers.demo_episodes["given"]
        if kept < given:  # said, not silent: a mixed-quality set's failed episodes train nothing here
            tqdm.write(f"{algorithm.name}: trains on the {kept} of {given} demonstrations that succeed")
        run.records["demo_episodes"] = [dict(buffers.demo_episodes)]
        progress = {"offline_updates": 0, "online_updates": 0, "env_steps": 0, "rounds": 0, "started": False}
        saved = {"buffer": None, "describe_start": False}
        run.records.setdefault("rounds", [])

        def state() -> dict[str, Any]:
            # the start is saved as the BC actor it is (DSRL's start acts through a NoiseActor, whose
            # weights a BC config does not rebuild): best.pt of a run whose start won loads as BC
            model = bc_actor if saved["describe_start"] else loss.actor
            return {
                "model": model.state_dict(),
                # the acting module's weights with the averaged ones (what load_actor(use_ema) rebuilds)
                "ema": None if ema is None or saved["describe_start"] else policy.state_dict(),
                "ema_n_averaged": None if ema is None else ema.n_averaged.clone(),
                "config": start_config if saved["describe_start"] else tuned_config,
                "source_checkpoint": str(cfg.checkpoint),
                "obs_shapes": {k: list(v) for k, v in bc_state["obs_shapes"].items()},
                "action_dim": int(bc_state["action_dim"]),
                "dataset": str(dataset),
                "loss": loss.state_dict(),
                "optimizer": optimizer.state_dict(),
                "buffers": buffers.state_dict(),
                "online_buffer": saved["buffer"],
                "progress": dict(progress),
            }

        def load(resumed: dict[str, Any]) -> None:
            loss.load_state_dict(resumed["loss"])
            if ema is not None:
                if resumed.get("ema_n_averaged") is None:
                    raise CheckpointMismatchError(  # a checkpoint from before the field
                        f"{run.latest} holds no EMA: resume it with finetune.ema_power=0"
                    )
                policy.load_state_dict(resumed["ema"])
                ema.n_averaged.copy_(resumed["ema_n_averaged"])
            optimizer.load_state_dict(resumed["optimizer"])
            if resumed.get("online_buffer"):
                buffers.load_online(run.ckpt_dir / resumed["online_buffer"])
            buffers.load_state_dict(resumed["buffers"])
            progress.update(resumed["progress"])
            saved["buffer"] = resumed.get("online_buffer")

        def step() -> int:  # one counter for both phases: offline updates, then env steps
            return progress["offline_updates"] + progress["env_steps"]

        def save(dump_online: bool) -> None:
            if dump_online:
                name = f"online_buffer_round{progress['rounds']}"
                buffers.dump_online(run.ckpt_dir / name)
                saved["buffer"] = name
            run.save()
            for old in run.ckpt_dir.glob("online_buffer_round*"):  # latest.pt names another one now
                if old.name != saved["buffer"]:
                    shutil.rmtree(old, ignore_errors=True)

        run.begin(state, load, step=step, total=int(off.steps) + int(on.steps))
        if not progress["started"]:  # the start competes: a run never reports a policy below it
            saved["describe_start"] = True
            # the BC checkpoint itself, as state() saves it when it wins (not the warm-up actor)
            run.validate(bc_actor, 0, phase="start", env_steps=0, updates=0)
            saved["describe_start"] = False
            progress["started"] = True

        with run.phase("offline"):
            while progress["offline_updates"] < off.steps:
                metrics = update(
                    loss, optimizer, target_update, buffers.sample_offline().to(device), ema, averaged
                )
                progress["offline_updates"] += 1
                n = progress["offline_updates"]
                if n % fcfg.log_every == 0 or n == off.steps:
                    run.log(step(), {**metrics, "env_steps": 0.0}, prefix="offline")
                if off.eval_every and n % off.eval_every == 0:
                    run.validate(policy, step(), phase="offline", env_steps=0, updates=n)
                if n == off.steps or (off.checkpoint_every and n % off.checkpoint_every == 0):
                    save(dump_online=False)
                run.step_done(step(), metrics, policy)  # a stop signal checkpoints here

        with run.phase("online"):
            if progress["env_steps"] < on.steps:
                with OnlineCollector(cfg, acting, device) as collector:
                    while progress["env_steps"] < on.steps:
                        acting.trained = progress["env_steps"] >= on.warmup_steps
                        t0 = time.perf_counter()
                        data = collector.collect(progress["rounds"])
                        collect_s = time.perf_counter() - t0
                        stored = buffers.add_collected(data)
                        frames = int(data.numel())
                        before = progress["env_steps"]
                        progress["env_steps"] += frames
                        progress["rounds"] += 1
                        # updates_per_step per env step past the warm-up (QC/RLPD start after it)
                        due = int(on.updates_per_step * max(0, progress["env_steps"] - on.warmup_steps))
                        t0, metrics = time.perf_counter(), {}
                        while progress["online_updates"] < due:
                            batch = buffers.sample_online().to(device)
                            metrics = update(loss, optimizer, target_update, batch, ema, averaged)
                            progress["online_updates"] += 1
                        update_s = time.perf_counter() - t0
                        updates = due - int(on.updates_per_step * max(0, before - on.warmup_steps))
                        record = {
                            **round_stats(data),
                            "env_steps": progress["env_steps"],
                            "steps_stored": stored,
                            "policy": "actor" if acting.trained else "start",
                            "env_steps_per_s": frames / collect_s,
                            "updates": updates,
                            "updates_per_s": updates / update_s if updates else None,
                            "online_windows": buffers.online_windows(),
                            "demo_only_batches": buffers.demo_only_batches,
                        }
                        run.records["rounds"].append(record)
                        numbers = {k: float(v) for k, v in record.items() if isinstance(v, (int, float))}
                        run.log(step(), {**metrics, **numbers}, prefix="online")
                        last = progress["env_steps"] >= on.steps
                        # an actor no update has touched (the warm-up) is not a candidate: FQL's mu is
                        # untrained then (measured: 0.02 against the start's 0.46 on PushCube)
                        trained = progress["offline_updates"] + progress["online_updates"] > 0
                        if _crossed(on.eval_every, before, progress["env_steps"]) and trained and not last:
                            run.validate(
                                policy,
                                step(),
                                phase="online",
                                env_steps=progress["env_steps"],
                                updates=progress["offline_updates"] + progress["online_updates"],
                            )
                        if _crossed(on.checkpoint_every, before, progress["env_steps"]) or last:
                            save(dump_online=True)
                        run.step_done(step(), metrics, policy)

        summary = {
            "task": cfg.task.name,
            "algorithm": fcfg.algorithm,
            "source_checkpoint": str(cfg.checkpoint),
            "offline_updates": progress["offline_updates"],
            "online_updates": progress["online_updates"],
            "env_steps": progress["env_steps"],
            "dataset": str(dataset),  # what it trained on (a file grown by shifted replays says their cost)
        }
        run.finish(policy, summary, plot=_plot)
    return 0


def _plot(run) -> None:
    """``finetune.png``: the critics' values against the run's step, and success against env steps
    (validations, and the collected episodes of each round)."""
    # optional dependency (app extra): plots
    import matplotlib

    matplotlib.use("Agg")
    # optional dependency (app extra): plots
    import matplotlib.pyplot as plt

    fig, (ax_q, ax_s) = plt.subplots(1, 2, figsize=(11, 3.8))
    history = run.history
    for key in ("q_data_mean", "target_mean", "td_error_abs"):
        ax_q.plot(history["step"], history[key], lw=1, label=key)
    ax_q.set_xlabel("offline updates + env steps")
    ax_q.legend()
    ax_q.grid(alpha=0.3)
    evals = [e for e in run.evals if e.get("split", "val") == "val"]
    if evals:
        ax_s.plot(
            [e.get("env_steps", 0) for e in evals],
            [e["success_once"] for e in evals],
            "o-",
            label="validation",
        )
    rounds = run.records.get("rounds", [])
    if rounds:
        # each env's first episode per round where recorded: the ended share counts a follow-up
        # episode only when it succeeds before the round's end (collect.round_stats)
        key = "first_episode_success" if "first_episode_success" in rounds[-1] else "episode_success"
        rate = [float("nan") if r.get(key) is None else r[key] for r in rounds]
        ax_s.plot([r["env_steps"] for r in rounds], rate, ".--", alpha=0.6, label="collected episodes")
    ax_s.set_xlabel("environment steps")
    ax_s.set_ylabel("success rate")
    ax_s.set_ylim(-0.05, 1.05)
    ax_s.grid(alpha=0.3)
    if evals or rounds:
        ax_s.legend()
    fig.tight_layout()
    fig.savefig(run.run_dir / "finetune.png", dpi=110)
    plt.close(fig)
