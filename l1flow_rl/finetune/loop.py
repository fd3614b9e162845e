"""``l1flow-rl finetune finetune=<algorithm> checkpoint=BC.pt``: a BC policy improved with rewards.

    l1flow-rl finetune finetune=qc checkpoint=runs/bc/checkpoints/best.pt task=maniskill_pickcube \\
        online.steps=100000 eval.episodes=100 online.eval_every=10000

1. The BC start is validated first and holds ``best.pt`` until a later model validates more than its
   standard error above it (``rule="start"``): a lead within the validation's noise never replaces it.
2. Offline (``offline.steps``): updates on the demonstrations' chunk windows (QC, FQL).
3. Online: rounds of ``online.frames_per_round`` env steps from ``online.num_envs`` worker envs (a
   TorchRL collector); the first ``online.warmup_steps`` are the BC start's, then each round is
   followed by ``online.updates_per_step`` updates per env step past the warm-up, on batches that
   take ``online.offline_fraction`` of their windows from the demonstrations (TorchRL's
   ``OfflineToOnlineReplayBuffer``). Each round logs env steps/s, updates/s, the critic
   diagnostics and the collected episodes' success; validation every ``online.eval_every`` env steps.
4. The chosen policy (under the "start" rule above) on the test seeds: ``eval.json``.

The loop talks to the algorithm through :class:`~l1flow_rl.finetune.base.Learner` (what it updates,
acts with and saves) and :class:`~l1flow_rl.finetune.base.FinetuneAlgorithm` (the data it needs).
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tqdm import tqdm

from l1flow_rl.config.overrides import overrides_under
from l1flow_rl.finetune.base import FinetuneAlgorithm, Learner
from l1flow_rl.finetune.buffers import RLBuffers
from l1flow_rl.finetune.collect import OnlineCollector, round_stats
from l1flow_rl.finetune.registry import builtin_algorithm_names, get_algorithm
from l1flow_rl.modules.actor import L1FlowActor
from l1flow_rl.workspace.checkpoint import (
    CheckpointMismatchError,
    ResumeMismatchError,
    load_actor,
    load_checkpoint,
)
from l1flow_rl.workspace.dataset import load_task_episodes, resolve_dataset
from l1flow_rl.workspace.distributed import resolve_device
from l1flow_rl.workspace.harness import Run, finished_run

__all__ = [
    "Finetune",
    "Start",
    "adopt_start_data",
    "check_extension",
    "load_start",
    "run_finetune",
    "start_dataset",
]

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


def run_finetune(cfg: DictConfig) -> int:
    """The job: the BC start and the algorithm, then inside the harness's run the start's validation,
    the offline phase, the online phase and the report. Returns the exit code. ``resume=auto`` skips a
    run directory that holds this very run, finished (a grid relaunched)."""
    if not cfg.checkpoint:
        print("l1flow-rl finetune: pass checkpoint=PATH (the L1 Flow BC checkpoint to fine-tune)")
        return 2
    device = resolve_device(cfg.device)
    start = load_start(cfg, device)
    algorithm = get_algorithm(cfg.finetune.algorithm)
    with open_dict(cfg):  # the algorithm's block with its defaults, as config.yaml and checkpoints record it
        cfg.finetune[algorithm.name] = algorithm.settings_of(cfg.finetune)
    done = finished_run(cfg, may_differ=other_blocks(algorithm))  # a grid relaunched: a finished job
    if done is not None:
        print(
            f"l1flow-rl finetune: {cfg.run_dir} holds this run, finished ({done.name}); skipped (resume=auto)"
        )
        return 0
    configs = acting_configs(cfg)
    with Run(
        cfg,
        job="finetune",
        device=device,
        may_change=(*MAY_CHANGE, *other_blocks(algorithm)),
        phases=("offline", "online"),
        log_every=0,  # logged per offline log_every updates and per online round, below
        checkpoint_every=0,  # checkpointed below: an online checkpoint also dumps the buffer
        eval_every=0,
        history_keys=("loss_qvalue", "q_data_mean", "target_mean", "td_error_abs", "env_steps"),
        rule="start",  # the start is validated first; a later model must beat it beyond its noise
    ) as run:
        if run.resumed is not None:  # before the data and the networks are built
            check_extension(run.resumed["progress"], cfg, str(run.latest))
        job = Finetune(cfg, run, start, algorithm, configs, device)
        run.begin(
            job.state,
            job.load,
            step=job.step,
            total=int(cfg.offline.steps) + int(cfg.online.steps),
            before_latest=job.dump_online,
        )
        job.validate_start()
        job.offline()
        job.online()
        run.finish(job.learner.acting, job.summary(), plot=_plot)
    return 0


@dataclass
class Start:
    """The BC checkpoint a run starts from: its actor (EMA weights), its checkpoint dict, and the
    ``demos.*``/``data.*`` keys the command line sets (the rest is the start's)."""

    actor: L1FlowActor
    state: dict[str, Any]
    given_data: list[str]


def load_start(cfg: DictConfig, device: torch.device) -> Start:
    """The BC checkpoint ``cfg.checkpoint``, checked against the task; ``cfg`` takes its network
    (``policy``, ``network``, ``encoder``) and, unless the command line sets them, its data
    (:func:`adopt_start_data`)."""
    state = load_checkpoint(cfg.checkpoint)
    actor, bc_cfg = load_actor(cfg.checkpoint, use_ema=True, map_location=device)
    _check_task(bc_cfg, cfg, str(cfg.checkpoint))
    with open_dict(cfg):  # the network is the checkpoint's
        cfg.policy = OmegaConf.merge(cfg.policy, bc_cfg.policy)
        if bc_cfg.get("network") is not None:
            cfg.network = OmegaConf.merge(cfg.network, bc_cfg.network)
        if bc_cfg.get("encoder") is not None and "encoder" in cfg:
            cfg.encoder = OmegaConf.merge(cfg.encoder, bc_cfg.encoder)
    given = [*overrides_under("demos"), *overrides_under("data")]
    adopt_start_data(cfg, bc_cfg, given)
    return Start(actor, state, given)


def acting_configs(cfg: DictConfig) -> dict[str, dict[str, Any]]:
    """What rebuilds each acting module (``load_actor``): the BC policy's config (``"start"``), and
    with the algorithm's block as ``policy.finetune`` (``"tuned"``)."""
    plain = OmegaConf.to_container(cfg, resolve=True)
    return {
        "start": {**plain, "policy": plain["policy"]},
        "tuned": {**plain, "policy": {**plain["policy"], "finetune": plain["finetune"]}},
    }


def other_blocks(algorithm: FinetuneAlgorithm) -> tuple[str, ...]:
    """The built-in algorithms' blocks other than ``algorithm``'s, which a resume may find changed: a
    run recorded before the per-algorithm folders holds every algorithm's block, a run now its own."""
    return tuple(f"finetune.{name}.*" for name in builtin_algorithm_names() if name != algorithm.name)


class Finetune:
    """One fine-tuning run inside the harness's :class:`~l1flow_rl.workspace.harness.Run`: the data, the
    :class:`~l1flow_rl.finetune.base.Learner`, the replay buffers and the progress, with the loop's
    steps as methods (:meth:`validate_start`, :meth:`offline`, :meth:`online`) and the harness's
    hooks (:meth:`state`, :meth:`load`, :meth:`step`)."""

    def __init__(
        self,
        cfg: DictConfig,
        run: Run,
        start: Start,
        algorithm: FinetuneAlgorithm,
        configs: dict[str, dict[str, Any]],
        device: torch.device,
    ) -> None:
        self.cfg, self.run, self.start, self.algorithm = cfg, run, start, algorithm
        self.configs, self.device = configs, device
        self.dataset = start_dataset(cfg, start.state, start.given_data)
        episodes = load_task_episodes(cfg, self.dataset)
        self.learner = Learner(
            algorithm,
            copy.deepcopy(start.actor),
            cfg.finetune,
            seed=int(cfg.seed),
            device=device,
            ema_n_averaged=start.state.get("ema_n_averaged"),
        )
        self.acting = ActingSwitch(self.learner.start, self.learner.acting)
        self.buffers = RLBuffers(
            cfg,
            episodes,
            self.learner.loss.rl_horizon,
            seed=int(cfg.seed),
            **algorithm.buffer_options(cfg.finetune),
        )
        kept, given = self.buffers.demo_episodes["kept"], self.buffers.demo_episodes["given"]
        if kept < given:  # said, not silent: a mixed-quality set's failed episodes train nothing here
            tqdm.write(f"{algorithm.name}: trains on the {kept} of {given} demonstrations that succeed")
        run.records["demo_episodes"] = [dict(self.buffers.demo_episodes)]
        run.records.setdefault("rounds", [])
        self.progress = {
            "offline_updates": 0,
            "online_updates": 0,
            "env_steps": 0,
            "rounds": 0,
            "started": False,
        }
        self.online_buffer: str | None = None  # the buffer dump the last checkpoint names
        self.describe_start = False  # while the start is validated: a checkpoint saves it as the BC actor

    # -- the harness's hooks ------------------------------------------------------------------------
    def step(self) -> int:
        """One counter for both phases: offline updates, then env steps."""
        return self.progress["offline_updates"] + self.progress["env_steps"]

    def updates(self) -> int:
        return self.progress["offline_updates"] + self.progress["online_updates"]

    def state(self) -> dict[str, Any]:
        state = self.learner.state_dict()
        if self.describe_start:
            # the start is saved as the BC actor it is (DSRL's start acts through a NoiseActor, whose
            # weights a BC config does not rebuild): best.pt of a run whose start won loads as BC
            state.update(model=self.start.actor.state_dict(), ema=None)
        return {
            **state,
            "config": self.configs["start" if self.describe_start else "tuned"],
            "source_checkpoint": str(self.cfg.checkpoint),
            "obs_shapes": {k: list(v) for k, v in self.start.state["obs_shapes"].items()},
            "action_dim": int(self.start.state["action_dim"]),
            "dataset": str(self.dataset),
            "buffers": self.buffers.state_dict(),
            "online_buffer": self.online_buffer,
            "progress": dict(self.progress),
        }

    def load(self, resumed: dict[str, Any]) -> None:
        self.learner.load_state_dict(resumed, str(self.run.latest))
        if resumed.get("online_buffer"):
            self.buffers.load_online(self.run.ckpt_dir / resumed["online_buffer"])
        self.buffers.load_state_dict(resumed["buffers"])
        self.progress.update(resumed["progress"])
        self.online_buffer = resumed.get("online_buffer")

    def dump_online(self) -> None:
        """The online buffer, dumped to a folder that the next ``latest.pt`` names (the harness calls
        this before every ``latest.pt``: a stop signal's checkpoint then holds every stored round)."""
        if self.progress["rounds"] == 0:
            return  # nothing collected yet
        name = f"online_buffer_round{self.progress['rounds']}"
        if name != self.online_buffer:
            self.buffers.dump_online(self.run.ckpt_dir / name)
            self.online_buffer = name

    def save(self) -> None:
        """``latest.pt``, with the online buffer it names; then the older dumps go."""
        self.run.save()
        for old in self.run.ckpt_dir.glob("online_buffer_round*"):  # latest.pt names another one now
            if old.name != self.online_buffer:
                shutil.rmtree(old, ignore_errors=True)

    # -- the loop -----------------------------------------------------------------------------------
    def validate_start(self) -> None:
        """The start competes for ``best.pt`` (``rule="start"``: kept unless clearly beaten)."""
        if self.progress["started"]:
            return
        self.describe_start = True
        # the BC checkpoint itself, as state() saves it when it wins (not the warm-up actor)
        self.run.validate(self.start.actor, 0, phase="start", env_steps=0, updates=0)
        self.describe_start = False
        self.progress["started"] = True

    def offline(self) -> None:
        """``offline.steps`` updates on the demonstrations, before any env step."""
        off, run = self.cfg.offline, self.run
        with run.phase("offline"):
            while self.progress["offline_updates"] < off.steps:
                batch = self.buffers.sample_offline().to(self.device)
                metrics = self.learner.update(batch, critic_only=bool(off.critic_only))
                self.progress["offline_updates"] += 1
                n = self.progress["offline_updates"]
                if n % self.cfg.finetune.log_every == 0 or n == off.steps:
                    run.log(self.step(), {**metrics, "env_steps": 0.0}, prefix="offline")
                if off.eval_every and n % off.eval_every == 0:
                    run.validate(self.learner.acting, self.step(), phase="offline", env_steps=0, updates=n)
                if n == off.steps or (off.checkpoint_every and n % off.checkpoint_every == 0):
                    self.save()
                run.step_done(self.step(), metrics, self.learner.acting)  # a stop signal checkpoints here

    def online(self) -> None:
        """Rounds of collection, each followed by its updates, until ``online.steps`` env steps."""
        with self.run.phase("online"):
            if self.progress["env_steps"] >= self.cfg.online.steps:
                return
            with OnlineCollector(self.cfg, self.acting, self.device) as collector:
                while self.progress["env_steps"] < self.cfg.online.steps:
                    self.online_round(collector)

    def updates_due(self, env_steps: int) -> int:
        """Online updates owed after ``env_steps``: ``updates_per_step`` per env step past the warm-up
        (QC/RLPD start after it)."""
        on = self.cfg.online
        return int(on.updates_per_step * max(0, env_steps - on.warmup_steps))

    def online_round(self, collector: OnlineCollector) -> None:
        """One round: collect (the start acts through the warm-up), store, update, log, validate, save."""
        on, run, progress = self.cfg.online, self.run, self.progress
        self.acting.trained = progress["env_steps"] >= on.warmup_steps
        t0 = time.perf_counter()
        data = collector.collect(progress["rounds"])
        collect_s = time.perf_counter() - t0
        stored = self.buffers.add_collected(data)
        frames = int(data.numel())
        before = progress["env_steps"]
        progress["env_steps"] += frames
        progress["rounds"] += 1
        due = self.updates_due(progress["env_steps"])
        t0, metrics = time.perf_counter(), {}
        while progress["online_updates"] < due:
            metrics = self.learner.update(self.buffers.sample_online().to(self.device))
            progress["online_updates"] += 1
        update_s = time.perf_counter() - t0
        updates = due - self.updates_due(before)
        record = {
            **round_stats(data),
            "env_steps": progress["env_steps"],
            "steps_stored": stored,
            "policy": "actor" if self.acting.trained else "start",
            "env_steps_per_s": frames / collect_s,
            "updates": updates,
            "updates_per_s": updates / update_s if updates else None,
            "online_windows": self.buffers.online_windows(),
            "demo_only_batches": self.buffers.demo_only_batches,
        }
        run.records["rounds"].append(record)
        numbers = {k: float(v) for k, v in record.items() if isinstance(v, (int, float))}
        run.log(self.step(), {**metrics, **numbers}, prefix="online")
        last = progress["env_steps"] >= on.steps
        # an actor no update has touched (the warm-up) is not a candidate: FQL's mu is untrained then
        if _crossed(on.eval_every, before, progress["env_steps"]) and self.updates() > 0 and not last:
            run.validate(
                self.learner.acting,
                self.step(),
                phase="online",
                env_steps=progress["env_steps"],
                updates=self.updates(),
            )
        if _crossed(on.checkpoint_every, before, progress["env_steps"]) or last:
            self.save()
        run.step_done(self.step(), metrics, self.learner.acting)

    def summary(self) -> dict[str, Any]:
        return {
            "task": self.cfg.task.name,
            "algorithm": self.cfg.finetune.algorithm,
            "source_checkpoint": str(self.cfg.checkpoint),
            "offline_updates": self.progress["offline_updates"],
            "online_updates": self.progress["online_updates"],
            "env_steps": self.progress["env_steps"],
            "dataset": str(
                self.dataset
            ),  # what it trained on (a file grown by shifted replays says their cost)
        }


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
