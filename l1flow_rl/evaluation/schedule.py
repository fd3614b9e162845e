"""Which episode each parallel env runs, and what each episode has accumulated so far.

Episode ``i`` always starts from seed ``seed + i``, whichever env runs it, so results do not depend
on the number of envs or on the order in which they finish.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from tensordict.utils import NestedKey

__all__ = ["REDUCTIONS", "Episode", "Schedule"]

#: how a simulator's per-step entry becomes one number per episode (SimulatorSpec.episode_metrics)
REDUCTIONS = ("max", "sum", "last", "any")


def _reduce(how: str, acc: float | bool | None, value: float) -> float | bool:
    if how == "max":
        return value if acc is None else max(acc, value)
    if how == "sum":
        return value if acc is None else acc + value
    if how == "last":
        return value
    return bool(value) or bool(acc)  # "any"


@dataclass
class Episode:
    """One episode's running totals: return, length, success flags and the simulator's own metrics."""

    index: int
    seed: int
    ret: float = 0.0
    length: int = 0
    success_once: bool = False
    success_at_end: bool = False
    #: the step (1-based) at which the episode first succeeded: how close a success came to the limit
    first_success_step: int | None = None
    extra: dict[str, float | bool | None] = field(default_factory=dict)
    frames: list[np.ndarray] | None = None
    record: dict[str, Any] = field(default_factory=dict)

    def add_step(
        self, reward: float, success: bool, extra: Mapping[str, float], metrics: Mapping[str, tuple[str, Any]]
    ) -> None:
        self.ret += reward
        self.length += 1
        if success and not self.success_once:
            self.first_success_step = self.length
        self.success_once |= success
        self.success_at_end = success
        for name, value in extra.items():
            self.extra[name] = _reduce(metrics[name][0], self.extra.get(name), value)

    def close(self, error: str | None) -> dict[str, Any]:
        """The episode's record; an episode that an error ended counts as a failure."""
        failed = error is not None
        # an error fails the episode's yes/no metrics; a metric no step reported stays None
        extra = {k: (bool(v) and not failed) if isinstance(v, bool) else v for k, v in self.extra.items()}
        return {
            "episode": self.index,
            "seed": self.seed,
            "success_once": self.success_once and not failed,
            "success_at_end": self.success_at_end and not failed,
            "first_success_step": None if failed else self.first_success_step,
            "return": self.ret,
            "length": self.length,
            **extra,
            "error": error,
            **self.record,
        }


class Schedule:
    """Hands out episodes (index, seed = seed + index) to env slots until ``episodes`` are done."""

    def __init__(
        self,
        episodes: int,
        seed: int,
        num_envs: int,
        video_episodes: int,
        metrics: Mapping[str, tuple[str, NestedKey]] | None = None,
    ) -> None:
        self.episodes, self.seed, self.video_episodes = episodes, seed, video_episodes
        self.metrics = dict(metrics or {})
        self.next_index = 0
        self.spare_seed = seed + episodes  # envs with nothing left to run reset from seeds past the range
        self.slots: list[Episode | None] = [None] * num_envs
        self.results: list[dict[str, Any]] = []

    def assign(self, slot: int) -> int:
        if self.next_index < self.episodes:
            ep = Episode(self.next_index, self.seed + self.next_index)
            ep.extra = dict.fromkeys(self.metrics)
            if ep.index < self.video_episodes:
                ep.frames = []
            self.slots[slot] = ep
            self.next_index += 1
            return ep.seed
        self.slots[slot] = None
        self.spare_seed += 1
        return self.spare_seed

    def finish(self, slot: int, error: str | None) -> Episode | None:
        """Close the episode in ``slot``; returns it (for its frames) or None if the slot was idle."""
        ep = self.slots[slot]
        if ep is None:
            return None
        self.results.append(ep.close(error))
        self.slots[slot] = None
        return ep

    @property
    def running(self) -> bool:
        return any(ep is not None for ep in self.slots)
