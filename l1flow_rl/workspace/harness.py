"""The run harness: what every job that trains shares, so that a job is its loop plus a config.

A job (``l1flow-rl train``, fine-tuning, a distillation step) builds its data and model, then
gives the harness ``state()`` (its checkpoint pieces: weights, optimiser, sampler or replay-buffer
state, its counters) and ``load(state)``. :class:`Run` does the rest:

- the run directory, locked to this process (:mod:`~l1flow_rl.workspace.run_lock`); seeding;
  the config record (``config.yaml``); the logger (``train.logger``);
- resume (``resume=true``): ``checkpoints/latest.pt`` continues if the config changes only fields
  of :data:`~l1flow_rl.workspace.checkpoint.RESUME_MAY_CHANGE` or of the job's ``may_change``,
  and then ends where an uninterrupted run ends (bit-exact on CPU); ``resume=auto`` (a grid's
  jobs) continues where ``latest.pt`` exists and starts fresh where not, and a job skips a run
  directory that already holds its finished run (:func:`finished_run`);
- atomic checkpoints: the job's pieces plus every RNG, the clock, the history, the evaluations,
  the best validation figure and the logger's state; a state holding a NaN is never written;
- a non-finite metric (loss, a ``loss_*`` term, ``grad_norm``) stops the run with
  :class:`~l1flow_rl.errors.RunDivergedError`, checked when metrics are read anyway (log,
  evaluation and checkpoint steps), so the loop never waits for the device on other steps;
- SIGTERM or SIGUSR1 (a cluster's pre-emption): a checkpoint at the current step, then
  :class:`~l1flow_rl.errors.RunPreempted`, which says how to resume;
- validation -> ``best.pt`` -> the test evaluation of the chosen weights (``eval.json``); with
  ``eval.enabled=false`` none of them (no evaluator, ``latest.pt`` only);
- ``summary.json`` (with the clocks over every invocation and the machine), ``history.json``, plots;
  both ``eval.json`` and ``summary.json`` carry a ``provenance`` block: the commits the run was
  trained at, its launcher, the time (:mod:`~l1flow_rl.workspace.provenance`).

Under torchrun every rank calls every method; rank 0 alone touches files, logs and evaluates
(:func:`~l1flow_rl.workspace.distributed.run_on_rank0`), and all ranks stop at the same step.

Example, a job whose counter is its updates (:mod:`l1flow_rl.workspace.train` is the real one)::

    def run_distill(cfg):
        with Run(cfg, job="distill", device=device, may_change=("distill.log_every",),
                 log_every=cfg.distill.log_every, checkpoint_every=1000, eval_every=5000) as run:
            student, opt, data = ...  # built after Run: it has seeded every RNG
            step = 0

            def load(state):
                nonlocal step
                student.load_state_dict(state["model"]); opt.load_state_dict(state["optimizer"])
                step = state["step"]

            run.begin(lambda: {"model": student.state_dict(), "optimizer": opt.state_dict(),
                               "step": step}, load, step=lambda: step, total=cfg.distill.steps)
            while step < cfg.distill.steps:
                loss = ...; step += 1
                run.step_done(step, {"loss": loss.detach()}, student)
            run.finish(student, {"task": cfg.task.name, "steps": step})

A loop counted in environment steps calls ``step_done(env_steps, metrics, actor)`` after each
collection round (cadences then count environment steps), or the parts on their own schedule:
:meth:`Run.log`, :meth:`Run.validate`, :meth:`Run.save` and :meth:`Run.check_signal`.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import random
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from omegaconf import DictConfig, OmegaConf

from l1flow_rl.errors import RunDirectoryError, RunDivergedError, RunPreempted
from l1flow_rl.evaluation.evaluator import sampler_record
from l1flow_rl.workspace.checkpoint import (
    check_resumable,
    config_differences,
    first_non_finite,
    get_rng_state,
    load_actor,
    load_checkpoint,
    save_checkpoint,
    set_rng_state,
)
from l1flow_rl.workspace.distributed import run_on_every_rank, run_on_rank0
from l1flow_rl.workspace.evaluator import SELECTION_RULES, PeriodicEvaluator, choose_evaluation
from l1flow_rl.workspace.logging import make_logger
from l1flow_rl.workspace.machine import machine_info
from l1flow_rl.workspace.provenance import run_provenance, source_commit
from l1flow_rl.workspace.report import format_summary, save_history, save_plots
from l1flow_rl.workspace.run_clock import RunClock
from l1flow_rl.workspace.run_lock import hold_run_dir

__all__ = ["SAME_RUN_MAY_DIFFER", "STOP_SIGNALS", "Run", "RunPreempted", "finished_run", "seed_everything"]

#: signals that stop a run with a checkpoint: SIGTERM (schedulers, ``kill``), SIGUSR1 (SLURM's
#: ``--signal`` warning before the time limit)
STOP_SIGNALS = (signal.SIGTERM, signal.SIGUSR1)


#: fields a finished run may differ in and still be the run asked for (``resume=auto`` skips it):
#: where things live, where it ran, how it was logged; never what was trained or measured
SAME_RUN_MAY_DIFFER: tuple[str, ...] = (
    "run_dir",
    "resume",
    "data_dir",
    "device",
    "train.logger",
    "train.project",
    "train.group",
    "train.run_name",
    "train.log_every",
    "train.prefetch",
    "train.compile",
)


def finished_run(
    cfg: DictConfig, may_differ: tuple[str, ...] = (), marker: str = "summary.json"
) -> Path | None:
    """With ``resume=auto``: the ``marker`` file (the last one the job writes) of the finished run in
    ``cfg.run_dir`` when its ``config.yaml`` is this config, but for :data:`SAME_RUN_MAY_DIFFER` and
    ``may_differ``; the job then skips it. None when the run directory holds no finished run, or
    ``resume`` is not ``auto``.

    A finished run of another setting (every group compared, ``network`` included) raises
    :class:`~l1flow_rl.errors.RunDirectoryError` naming each field: a grid relaunched with another
    budget must not read an old figure back as the new one.
    """
    if not (isinstance(cfg.get("resume"), str) and cfg.resume == "auto"):
        return None
    run_dir = Path(cfg.run_dir)
    done, saved = run_dir / marker, run_dir / "config.yaml"
    if not done.is_file():
        return None
    if not saved.is_file():
        raise RunDirectoryError(
            f"run_dir {str(run_dir)!r} holds a finished run ({done}) but no config.yaml saying what it ran; "
            "move it away, or choose another run_dir"
        )
    saved_cfg = OmegaConf.to_container(OmegaConf.load(saved), resolve=False)
    diffs = config_differences(
        saved_cfg, cfg, (*SAME_RUN_MAY_DIFFER, *may_differ), saved_as="the finished run"
    )
    if diffs:
        raise RunDirectoryError(
            f"resume=auto: run_dir {str(run_dir)!r} holds a finished run of another setting:\n  "
            + "\n  ".join(diffs)
            + "\nMove it away or choose another run_dir (a grid: another hydra.sweep.dir); resume=true "
            "continues it where only fields a resume may change differ (evaluation settings: the test "
            "is run again)."
        )
    return done


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


class Run:
    """One run of a job in ``cfg.run_dir``: use it as a context manager (see the module docstring).

    Entering it locks the run directory (rank 0), seeds every RNG with ``seed`` (default
    ``cfg.seed`` + rank), reads and checks the checkpoint that ``resume=true`` continues
    (:attr:`resumed`), makes the evaluator (``cfg.eval``; before any data is made, so a bad
    protocol fails first) and catches :data:`STOP_SIGNALS`.

    Args:
        cfg: the run's composed config (``run_dir``, ``resume``, ``seed``, ``train.logger``, ``eval``).
        job: the job's name (messages, the logger's default run name).
        device: where evaluations run.
        may_change: config fields (``fnmatch`` patterns) this job lets a resume change, beside
            :data:`~l1flow_rl.workspace.checkpoint.RESUME_MAY_CHANGE`.
        phases: the clock's phases (:class:`~l1flow_rl.workspace.run_clock.RunClock`).
        log_every, checkpoint_every, eval_every: cadences of :meth:`step_done`, in the job's step
            unit (0 turns checkpoints or validation during training off).
        history_keys: the metrics kept in ``history.json`` beside ``step`` (all are logged).
        seed: every RNG's seed (default ``cfg.seed`` + the rank: each rank its own sample stream).
        rule: which validated model ``best.pt`` keeps (``SELECTION_RULES``): ``"latest"`` of equals
            for training, ``"start"`` where the first evaluation is a start that a later model must
            beat by more than the validation's standard error.
    """

    def __init__(
        self,
        cfg: DictConfig,
        *,
        job: str,
        device: torch.device,
        may_change: tuple[str, ...] = (),
        phases: tuple[str, ...] = ("train",),
        log_every: int = 50,
        checkpoint_every: int = 1000,
        eval_every: int = 0,
        history_keys: tuple[str, ...] = ("loss", "lr"),
        seed: int | None = None,
        rule: str = "earliest",
    ) -> None:
        if rule not in SELECTION_RULES:
            raise ValueError(f"rule={rule!r}; expected one of {SELECTION_RULES}")
        self.rule = rule
        self.cfg, self.job, self.device, self.may_change = cfg, job, device, tuple(may_change)
        self.rank = dist.get_rank() if dist.is_available() and dist.is_initialized() else 0
        self.seed = cfg.seed + self.rank if seed is None else seed
        self.run_dir = Path(cfg.run_dir)
        self.ckpt_dir = self.run_dir / "checkpoints"
        self.latest, self.best_path = self.ckpt_dir / "latest.pt", self.ckpt_dir / "best.pt"
        # resume=auto: continue where a checkpoint exists, else start
        self.resume = cfg.resume is True or (cfg.resume == "auto" and self.latest.is_file())
        #: the source commits of every invocation, and the steps it was resumed from (provenance in
        #: eval.json and summary.json)
        self.commits: list[str] = []
        self.resumed_at: list[int] = []
        self.config = OmegaConf.to_container(cfg, resolve=True)  # recorded in every checkpoint
        self.log_every, self.checkpoint_every, self.eval_every = log_every, checkpoint_every, eval_every
        self.phases = phases
        self.history: dict[str, list[float]] = {"step": [], **{k: [] for k in history_keys}}
        self.evals: list[dict[str, Any]] = []
        #: other lists the job keeps (e.g. collection rounds): checkpointed and in history.json
        self.records: dict[str, list[Any]] = {}
        #: entries the job adds to eval.json and summary.json, of the weights the test scored (e.g. the
        #: training ledger): called with their step, an earlier one than the run's when validation chose
        #: ``best.pt``
        self.report_for_weights: Callable[[int], dict[str, Any]] | None = None
        #: keys of those entries that the files keep but the printed summary leaves out
        self.report_unprinted: set[str] = set()
        self.best = -math.inf
        self._validates = bool(cfg.eval.enabled)  # the same on every rank (the evaluator: rank 0 only)
        self.resumed: dict[str, Any] | None = None
        self.evaluator: Any = None  # rank 0 only
        self.logger: Any = None  # rank 0 only
        self.clock: RunClock | None = None
        self._stack = contextlib.ExitStack()
        self._signal: int | None = None
        self._state_fn: Callable[[], dict[str, Any]] | None = None
        self._step_fn: Callable[[], int] = lambda: 0
        self._before_latest: Callable[[], None] | None = None
        self._prev_step = 0  # the step of the previous step_done: cadences fire on crossing a multiple
        self._saved_step: int | None = None  # the step latest.pt holds
        self._bar: Any = None
        self._t_begin, self._first_step = 0.0, 0

    # -- entering and leaving ----------------------------------------------------------------
    def __enter__(self) -> Run:
        self._stack.__enter__()
        try:
            self._catch_signals()
            seed_everything(self.seed)
            run_on_rank0(self._preflight, "locking and checking the run directory, making the evaluator")
            self.resumed = run_on_every_rank(self._read_resumed, "reading the checkpoint to resume")
            self.clock = RunClock(self.resumed.get("elapsed") if self.resumed else None, self.phases)
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stack.__exit__(*exc)

    def _catch_signals(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # Python delivers signals to the main thread only

        def stop(signum: int, frame: Any) -> None:
            if self._signal is not None:  # a second signal: stop now, as without the harness
                signal.signal(signum, signal.SIG_DFL)
                signal.raise_signal(signum)
            self._signal = signum
            # Straight to the descriptor: a handler writing through sys.stderr could re-enter a
            # write the loop (the progress bar) had begun, which Python refuses.
            note = f"\n{signal.Signals(signum).name}: {self.job} will checkpoint and stop after this step\n"
            with contextlib.suppress(OSError):
                os.write(2, note.encode())

        for signum in STOP_SIGNALS:
            previous = signal.signal(signum, stop)
            self._stack.callback(signal.signal, signum, previous)

    def _preflight(self) -> None:
        self._stack.enter_context(hold_run_dir(self.run_dir))
        if not self.resume and self.latest.is_file():
            raise RunDirectoryError(
                f"run_dir {str(self.run_dir)!r} already holds a run ({self.latest}); pass resume=true to "
                "continue it, or choose another run_dir"
            )
        if self._validates:
            self.evaluator = PeriodicEvaluator(self.cfg, self.device)
            self._stack.callback(self.evaluator.close)

    def _read_resumed(self) -> dict[str, Any] | None:
        if not self.resume:
            return None
        if not self.latest.is_file():
            raise RunDirectoryError(
                f"resume=true but {str(self.latest)!r} does not exist; pass the run's directory as "
                "run_dir=... (every run gets a new directory by default), or drop resume=true to start fresh"
            )
        state = load_checkpoint(self.latest)
        # the run's own config: "config", or "run_config" where the job's "config" rebuilds its model
        saved = state.get("run_config", state["config"])
        check_resumable(saved, self.cfg, str(self.latest), self.may_change)
        return state

    # -- the job's state -----------------------------------------------------------------------
    def begin(
        self,
        state: Callable[[], dict[str, Any]],
        load: Callable[[dict[str, Any]], None],
        *,
        step: Callable[[], int],
        total: int | None = None,
        before_latest: Callable[[], None] | None = None,
    ) -> None:
        """Hand over the job's checkpoint pieces (``state()``; ``load`` restores them) and its
        counter (``step()``), once the job has built everything that draws random numbers. A
        resumed run is restored here (the job's pieces, then every RNG, the history, the
        evaluations); then ``config.yaml`` is written and the logger opened. ``total``: the
        progress bar's length. ``before_latest()``: writes what ``latest.pt`` names beside itself
        (fine-tuning's replay buffer), called before every ``latest.pt``, whatever wrote it (a
        cadence, the end, a stop signal), so the checkpoint never names an older dump."""
        self._state_fn, self._step_fn, self._before_latest = state, step, before_latest
        if self.resumed is not None:
            load(self.resumed)
            set_rng_state(self.resumed["rng"])
            self.history, self.evals = self.resumed["history"], self.resumed["evals"]
            self.best = float(self.resumed["best"])
            self.records = dict(self.resumed.get("records") or {})
            self.commits = list(self.resumed.get("commits") or [])
            self.resumed_at = [*(self.resumed.get("resumed_at") or []), step()]
            self.clock.resumed_at(step())
            self._saved_step = step()
        if (commit := source_commit()) and commit not in self.commits[-1:]:
            self.commits.append(commit)
        self._prev_step = self._first_step = step()
        run_on_rank0(self._open_record, "writing config.yaml and opening the logger")
        from tqdm import tqdm  # the app extra (jobs run from the CLI); the core modules import without it

        self._bar = tqdm(
            total=total, initial=self._first_step, desc=self.job, disable=self.rank != 0, dynamic_ncols=True
        )
        self._stack.callback(self._bar.close)
        self._t_begin = time.perf_counter()

    def _open_record(self) -> None:
        if self.resumed is not None:  # a finished run resumed (to extend it) keeps its earlier report
            for name in ("eval.json", "summary.json"):
                done = self.run_dir / name
                if done.is_file():
                    done.replace(done.with_name(f"{done.stem}_step{self._first_step}.json"))
        OmegaConf.save(self.cfg, self.run_dir / "config.yaml")
        tcfg = self.cfg.train
        self.logger = make_logger(
            tcfg.logger,
            self.run_dir,
            self.resumed.get("logger") if self.resumed else None,
            project=tcfg.project,
            group=tcfg.group,
            run_name=tcfg.run_name,
            default_name=self.job,
            config=self.config,
        )
        if self.evaluator is not None:
            self.evaluator.logger = self.logger  # every metric of every evaluation, and its videos

    @contextlib.contextmanager
    def phase(self, name: str) -> Iterator[None]:
        """Count the block's seconds under ``name`` (one of ``phases``) in ``summary.json``."""
        self.clock.start(name)
        try:
            yield
        finally:
            self.clock.stop(name)

    @property
    def step(self) -> int:
        return self._step_fn()

    def state(self) -> dict[str, Any]:
        """A checkpoint: the job's pieces plus the harness's (RNG, clock, history, evaluations, best)."""
        state = self._state_fn()
        if "config" in state:  # the job's own (fine-tuning: the config that rebuilds its model)
            state["run_config"] = self.config
        state.setdefault("config", self.config)
        state.update(
            rng=get_rng_state(),
            history=self.history,
            evals=self.evals,
            records=self.records,
            commits=self.commits,
            resumed_at=self.resumed_at,
            best=self.best,
            elapsed=self.clock.totals(),
            logger=self.logger.state_dict() if hasattr(self.logger, "state_dict") else None,
        )
        return state

    # -- one step ---------------------------------------------------------------------------
    def _crossed(self, every: int, step: int) -> bool:
        return every > 0 and step // every > self._prev_step // every

    def step_done(
        self, step: int, metrics: Mapping[str, torch.Tensor | float], actor: Any, *, last: bool = False
    ) -> None:
        """After each update (or collection round): log, validate and checkpoint on their cadences
        (``last``: the final step, logged and checkpointed; its validation is :meth:`finish`'s),
        stop on a signal, raise on a non-finite metric. Reads ``metrics`` to the host only then."""
        log = last or self._crossed(self.log_every, step)
        save = last or self._crossed(self.checkpoint_every, step)
        validate = self._validates and not last and self._crossed(self.eval_every, step)
        self._prev_step = step
        if self._bar is not None:
            self._bar.update(step - self._bar.n)
        # Under torchrun the ranks agree on a stop at a due step; alone, any step may stop.
        alone = not (dist.is_available() and dist.is_initialized())
        if not (log or save or validate or (alone and self._signal is not None)):
            return

        def rank0() -> int | None:
            if log:
                self._log(step, metrics)
            else:  # a checkpoint or an evaluation is due: its metrics are checked first
                self._read(step, metrics)
            if validate:
                self._check_state(self.state())  # NaN weights would fail in the simulator instead
                self._validate(actor, step)
            if save:
                self._save(self.latest)
            return self._stop_here()

        self._raise_if_stopped(run_on_rank0(rank0, f"logging/evaluating/checkpointing at step {step}"))

    def _read(self, step: int, metrics: Mapping[str, torch.Tensor | float]) -> dict[str, float]:
        values = {k: float(v) for k, v in metrics.items()}  # waits for the device: due steps only
        bad = [k for k, v in values.items() if not math.isfinite(v)]
        if bad:
            bad.sort(key=lambda k: (not k.startswith("loss_"), k))  # the terms first: they name the cause
            self._diverged(step, ", ".join(f"{k}={values[k]}" for k in bad))
        return values

    def _check_state(self, state: Mapping[str, Any]) -> None:
        """Raise unless every float tensor of ``state`` is finite (before it is saved or evaluated)."""
        bad = first_non_finite(state)
        if bad is not None:
            self._diverged(self.step, f"the weights or optimiser entry {bad} is not finite")

    def _diverged(self, step: int, what: str) -> None:
        kept = (
            f"the last checkpoint, {self.latest}, is from step {self._saved_step} and finite"
            if self._saved_step is not None
            else "no checkpoint was written"
        )
        raise RunDivergedError(
            f"{self.job} diverged: at step {step} {what} (checked every {self.log_every} steps and before "
            f"each checkpoint or evaluation); {kept}. Lower the learning rate, or clip gradients"
        )

    def log(self, step: int, metrics: Mapping[str, torch.Tensor | float], prefix: str = "train") -> None:
        """Read ``metrics`` to the host, check them, keep ``history_keys`` and log them all under
        ``prefix/`` (every rank calls it; rank 0 logs)."""
        run_on_rank0(lambda: self._log(step, metrics, prefix), f"logging at step {step}")

    def _log(self, step: int, metrics: Mapping[str, torch.Tensor | float], prefix: str = "train") -> None:
        values = self._read(step, metrics)
        self.history["step"].append(step)
        for key in self.history:
            if key != "step":
                self.history[key].append(values.get(key, math.nan))
        for key, value in values.items():
            self.logger.log_scalar(f"{prefix}/{key}", value, step=step)
        rate = (step - self._first_step) / max(time.perf_counter() - self._t_begin, 1e-9)
        shown = {k: f"{values[k]:.4g}" for k in self.history if k in values}
        self._bar.set_postfix(**shown, it_s=f"{rate:.1f}", refresh=False)

    def validate(self, actor: Any, step: int, **row: Any) -> dict[str, Any] | None:
        """Evaluate ``actor`` on the validation seeds; the best so far becomes ``best.pt``. ``row``:
        extra fields of its history row (e.g. ``env_steps``). Every rank calls it; rank 0 evaluates."""
        if not self._validates:
            return None
        return run_on_rank0(lambda: self._validate(actor, step, **row), f"validating at step {step}")

    def _validate(self, actor: Any, step: int, **row: Any) -> dict[str, Any]:
        result = self.evaluator(actor, step, split="val")
        self.evals.append({**self.evaluator.history_row(result), **row})
        value, name = result[self.evaluator.headline], self.evaluator.headline
        self._bar.write(f"step {step}: validation {name}={value:.3f} over {result['episodes']} episodes")
        val = [e for e in self.evals if e.get("split", "val") == "val"]
        if choose_evaluation(val, name, self.rule) is val[-1]:
            self.best = value
            self._save(self.best_path)
        return result

    def save(self) -> None:
        """Write ``latest.pt`` now (every rank calls it; rank 0 writes)."""
        run_on_rank0(lambda: self._save(self.latest), "writing the checkpoint")

    def _save(self, path: Path) -> None:
        if path == self.latest and self._before_latest is not None:
            self._before_latest()
        state = self.state()
        self._check_state(state)
        save_checkpoint(path, state)
        if path == self.latest:
            self._saved_step = self.step

    def check_signal(self) -> None:
        """If a stop signal came: ``latest.pt`` at this step, then :class:`RunPreempted`. Under
        torchrun every rank calls it at the same step (rank 0's signal decides)."""
        self._raise_if_stopped(run_on_rank0(self._stop_here, "checking for a stop signal"))

    def _stop_here(self) -> int | None:
        if self._signal is not None and self.step > 0 and self._saved_step != self.step:
            self._save(self.latest)
        return self._signal

    def _raise_if_stopped(self, signum: int | None) -> None:
        if signum is not None:
            saved = self.latest if self.latest.is_file() else None
            raise RunPreempted(signum, self.step, self.run_dir, saved)

    # -- the end -----------------------------------------------------------------------------
    def finish(
        self,
        actor: Any,
        summary: dict[str, Any],
        *,
        load_chosen: Callable[[Path], Any] | None = None,
        plot: Callable[[Run], Any] | None = None,
    ) -> dict[str, Any]:
        """The final model competes on validation; the chosen weights (``best.pt``, read back with
        ``load_chosen``, by default :func:`~l1flow_rl.workspace.checkpoint.load_actor`'s EMA
        weights, when they are not the final ones) play the test seeds (``eval.json``); then
        ``summary.json`` (``summary``, the test figures, the clocks, the machine), ``history.json``
        and the plots (``plot(run)``; default: loss and success curves). Returns the summary."""
        if self._bar is not None:
            self._bar.close()
        final = lambda: self._final_validation(actor)  # noqa: E731
        self._raise_if_stopped(run_on_rank0(final, "validating the final model"))
        report = lambda: self._report(actor, dict(summary), load_chosen, plot)  # noqa: E731
        return run_on_rank0(report, "evaluating the chosen model and writing the report")

    def _final_validation(self, actor: Any) -> int | None:
        step = self.step
        if self.evaluator is not None:
            val = [e for e in self.evals if e.get("split", "val") == "val"]
            if not val:  # no validation during training: the final model is the only candidate
                self._save(self.best_path)
            elif not any(e["step"] == step for e in val):  # (a resumed run may have done it already)
                self._validate(actor, step)
        self._save(self.latest)  # with the final evaluations: a run stopped from here on skips them
        return self._signal

    def _report(self, actor: Any, summary: dict[str, Any], load_chosen: Any, plot: Any) -> dict[str, Any]:
        step, ev = self.step, self.evaluator
        selection = ev.selection(self.evals, step, rule=self.rule) if ev is not None else {"step": step}
        extra = self.report_for_weights(selection["step"]) if self.report_for_weights is not None else {}
        if ev is not None:
            chosen = actor
            if selection["step"] != step:
                load = load_chosen or (lambda p: load_actor(p, use_ema=True, map_location=self.device)[0])
                chosen = load(self.best_path)
            result = ev(chosen, step, video_dir=self.run_dir / "videos", split="test")
            ev.close()
            # the test row names the weights it scored (not the run's last step) and their interval
            ci95 = {k: list(v) for k, v in result.get("ci95", {}).items() if k.startswith("success")}
            self.evals.append({**ev.history_row(result), "weights_step": selection["step"], "ci95": ci95})
            result = {**result, "selection": selection, "sampler": sampler_record(chosen)}
            result.update(extra)
            result["provenance"] = run_provenance(self.commits, self.resumed_at)
            (self.run_dir / "eval.json").write_text(json.dumps(result, indent=2))
            summary.update(
                success_once=result["success_once"],
                success_at_end=result["success_at_end"],
                eval_episodes=result["episodes"],
                chunk_latency_ms_median=result.get("latency_ms_median"),
            )
        summary.update(extra)
        # Seconds over every invocation of the run; CPU is the budget when runs share the machine.
        summary.update(self.clock.summary())
        summary["machine"] = machine_info(self.device)  # threads and load as this invocation ended
        summary["provenance"] = run_provenance(self.commits, self.resumed_at)
        (plot or (lambda run: save_plots(run.history, run.evals, run.run_dir)))(self)
        save_history(self.history, self.evals, self.run_dir, **self.records)
        (self.run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
        print(format_summary({k: v for k, v in summary.items() if k not in self.report_unprinted}))
        print(f"run directory: {self.run_dir}")
        return summary
