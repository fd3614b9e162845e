"""The evaluation of one run, resolved once: protocol + ``eval`` config + command line -> which
env, which seeds for validation and for test, which headline, and what eval.json records."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.utils import NestedKey

from l1flow_rl.config import TaskConfig
from l1flow_rl.config.overrides import overrides_under
from l1flow_rl.envs import make_env
from l1flow_rl.envs.registry import get_simulator
from l1flow_rl.evaluation.evaluator import BUILTIN_METRICS
from l1flow_rl.evaluation.protocols import EvalProtocol, get_protocol
from l1flow_rl.evaluation.videos import video_episodes_to_film
from l1flow_rl.utils.device import resolve_device

__all__ = ["SPLITS", "EvalPlan", "check_seed_ranges", "eval_config_problems", "resolve_plan", "task_from"]

#: "val": seeds that choose the best checkpoint; "test": separate seeds for the reported figures
SPLITS = ("val", "test")


def check_seed_ranges(val_seed: int, val_episodes: int, seed: int, episodes: int) -> None:
    """Validation and test seeds must not overlap, else the test figure is not held out."""
    if val_seed < seed + episodes and seed < val_seed + val_episodes:
        raise ValueError(
            f"eval.val_seed={val_seed} (+{val_episodes} episodes) overlaps the test seeds eval.seed={seed} "
            f"(+{episodes} episodes); choose disjoint ranges so that the test figures stay held out"
        )


def eval_config_problems(cfg: DictConfig, command: str) -> list[str]:
    """The ``eval`` group's values that cannot work for ``command`` (config time, one line each):
    ``eval.enabled=false`` for ``eval``, and validation seeds that overlap the test seeds (unless
    evaluation is off)."""
    ev = cfg.get("eval") if isinstance(cfg, DictConfig) else None
    if ev is None:
        return []
    if not ev.get("enabled", True):
        if command == "eval":
            return ["eval.enabled=False: l1flow-rl eval evaluates; drop eval.enabled=false"]
        return []  # no episode runs: the seeds are not used
    problems = []
    try:
        check_seed_ranges(ev.val_seed, ev.val_episodes or ev.episodes, ev.seed, ev.episodes)
    except ValueError as err:
        problems.append(str(err))
    return problems


@dataclass
class EvalPlan:
    """Everything an evaluation of a run needs, for both splits."""

    protocol: EvalProtocol
    task: TaskConfig  # the evaluation env's task (protocol fields applied)
    episodes: int  # test
    seed: int
    val_episodes: int
    val_seed: int
    num_envs: int
    env_device: torch.device
    deterministic: bool
    video_episodes: int
    video_fps: int
    episode_metrics: dict[str, tuple[str, NestedKey]] = field(default_factory=dict)
    deviations: list[str] = field(default_factory=list)

    @property
    def headline(self) -> str:
        return self.protocol.headline

    def split(self, name: str) -> tuple[int, int]:
        """(episodes, first seed) of ``"val"`` or ``"test"``."""
        if name not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {name!r}")
        return (self.val_episodes, self.val_seed) if name == "val" else (self.episodes, self.seed)

    def make_env(self, obs_horizon: int):
        return make_env(
            self.task,
            num_envs=self.num_envs,
            device=self.env_device,
            obs_horizon=obs_horizon,
            **dict(self.protocol.env_options),
        )

    def record(self, split: str, result: Mapping[str, Any]) -> dict[str, Any]:
        """The head of eval.json: which split and seeds, the protocol as applied, the headline."""
        episodes, seed = self.split(split)
        name = self.headline
        return {
            "split": split,
            "split_seeds": {"first": seed, "episodes": episodes},
            "protocol": {
                **self.protocol.record(),
                "episodes": episodes,
                "max_episode_steps": self.task.max_episode_steps,
                "env_device": str(self.env_device),
                "deviations": list(self.deviations),
            },
            "headline": {"metric": name, "value": result.get(name), "ci95": result.get("ci95", {}).get(name)},
        }


def resolve_plan(
    cfg: DictConfig,
    task: TaskConfig,
    device: str | torch.device,
    overrides: Sequence[str] | None = None,
) -> EvalPlan:
    """The evaluation of ``task`` under ``cfg.eval`` and its protocol. A value the user gave on the
    command line (``overrides``, default: the running hydra job's) beats the protocol's, and the
    plan lists it under ``deviations``."""
    ev = cfg.eval
    protocol = get_protocol(ev.protocol)
    protocol.check_task(task)
    given = set(overrides_under("eval", overrides)) | set(overrides_under("task", overrides))
    deviations: list[str] = []

    def pick(key: str, configured: Any, by_protocol: Any) -> Any:
        if by_protocol is None or configured == by_protocol:
            return configured
        if key in given:
            deviations.append(f"{key}={configured} (protocol {protocol.name!r}: {by_protocol})")
            return configured
        return by_protocol

    episodes = int(pick("eval.episodes", ev.episodes, protocol.episodes))
    seed = int(pick("eval.seed", ev.seed, protocol.seed))
    fields = dict(protocol.task_fields(task)) if protocol.task_fields is not None else {}
    fields = {k: pick(f"task.{k}", getattr(task, k), v) for k, v in fields.items()}
    eval_task = dataclasses.replace(task, **fields) if fields else task
    val_episodes = int(ev.val_episodes) or episodes
    check_seed_ranges(int(ev.val_seed), val_episodes, seed, episodes)
    metrics = dict(get_simulator(task.simulator).episode_metrics)
    known = set(BUILTIN_METRICS) | set(metrics)
    if protocol.headline not in known:
        raise ValueError(
            f"eval.protocol={protocol.name!r} reports {protocol.headline!r} first, but simulator "
            f"{task.simulator!r} yields only {sorted(known)}"
        )
    run_device = resolve_device(device)
    configured_env = ev.get("env_device")
    if configured_env is not None:
        try:
            torch.device(configured_env)
        except RuntimeError as err:
            raise ValueError(
                f"eval.env_device={configured_env!r}: expected a torch device such as 'cpu' or 'cuda' ({err})"
            ) from None
        env_device = pick("eval.env_device", str(configured_env), protocol.env_device)
    else:
        env_device = protocol.env_device
    video = video_episodes_to_film(ev.video_episodes, run_device)
    return EvalPlan(
        protocol=protocol,
        task=eval_task,
        episodes=episodes,
        seed=seed,
        val_episodes=val_episodes,
        val_seed=int(ev.val_seed),
        num_envs=int(ev.num_envs),
        env_device=torch.device(env_device) if env_device else run_device,
        deterministic=bool(ev.deterministic),
        video_episodes=int(video),
        video_fps=int(ev.video_fps),
        episode_metrics=metrics,
        deviations=deviations,
    )


def task_from(cfg: DictConfig | Mapping[str, Any]) -> TaskConfig:
    """A validated :class:`TaskConfig` from a task node (DictConfig or plain dict)."""
    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(TaskConfig), cfg))  # type: ignore[return-value]
