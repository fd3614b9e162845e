"""``l1flow-rl demos``: make ``demos.num`` demonstrations of the task with its simulator's expert."""

from __future__ import annotations

import sys
import time

from omegaconf import DictConfig, OmegaConf

from l1flow_rl.experts.options import demo_options
from l1flow_rl.experts.registry import DemoGenerationError, ensure_demos

__all__ = ["run_demos"]


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
