"""``l1flow-rl demos``: make ``demos.num`` demonstrations of the task with its simulator's expert."""

from __future__ import annotations

import sys
import time

from omegaconf import DictConfig, OmegaConf

from l1flow_rl.experts.registry import DemoGenerationError, ensure_demos, get_expert

__all__ = ["demo_options", "run_demos"]


def demo_options(cfg: DictConfig, task) -> dict:
    """The ``demos`` group's options that the task's expert takes (``num`` and ``seed`` are
    positional; the rest, e.g. ManiSkill's ``max_consecutive_failures``, only where accepted)."""
    spec = get_expert(task)
    demos = OmegaConf.to_container(cfg.demos, resolve=True)
    if demos.get("quality", "expert") != "expert" and "quality" not in spec.options:
        raise DemoGenerationError(
            f"demos.quality={demos['quality']!r}: the {spec.simulator} expert makes expert demonstrations "
            "only (mixed quality: robosuite and ManiSkill tasks)"
        )
    if demos.get("shifted_replays", 0) and "shifted_replays" not in spec.options:
        raise DemoGenerationError(
            f"demos.shifted_replays={demos['shifted_replays']}: the {spec.simulator} expert makes no shifted "
            "replays (robosuite tasks with absolute control)"
        )
    return {k: v for k, v in demos.items() if k not in ("num", "seed") and k in spec.options}


def run_demos(cfg: DictConfig) -> int:
    task = OmegaConf.to_object(cfg.task) if isinstance(cfg.task, DictConfig) else cfg.task
    start = time.perf_counter()
    try:
        path = ensure_demos(
            task, int(cfg.demos.num), cfg.data_dir, seed=int(cfg.demos.seed), **demo_options(cfg, task)
        )
    except DemoGenerationError as err:
        print(f"l1flow-rl demos: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(
            "l1flow-rl demos: interrupted before the demonstrations were complete; run it again (experts "
            "that cache finished batches, like ManiSkill's, resume from them)",
            file=sys.stderr,
        )
        return 130
    print(
        f"{cfg.demos.num} demonstrations of {task.env_id} ready in {time.perf_counter() - start:.1f} s",
        file=sys.stderr,
    )
    print(path)
    return 0
