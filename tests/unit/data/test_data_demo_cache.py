"""The demonstration cache's bookkeeping (no simulator): batch sizing, the seed chain, outcomes."""

from __future__ import annotations

import json

from l1flow_rl.config import TaskConfig
from l1flow_rl.experts.maniskill.demos import MAX_BATCH, MIN_BATCH, _batch_sizes, _Generator, _planned_chain


def test_batch_sizes_split_rounds_over_workers():
    assert _batch_sizes(3, [], failures_left=50, workers=2) == [4]  # prior rate 0.9: one small batch
    sizes = _batch_sizes(30, [], failures_left=50, workers=2)
    assert len(sizes) == 2 and sum(sizes) == 37 and max(sizes) - min(sizes) <= 1
    assert _batch_sizes(1000, [], failures_left=1000, workers=4) == [MAX_BATCH] * 4
    assert _batch_sizes(30, [], failures_left=3, workers=2) == [3]  # never past the failure limit
    low = [(s, s % 2 == 0, None) for s in range(20)]  # half the seeds worked
    assert sum(_batch_sizes(10, low, failures_left=50, workers=1)) == 21
    assert all(k >= MIN_BATCH for k in _batch_sizes(17, [], failures_left=50, workers=4))


def _write_batch(planned, first, attempts, replayed_seeds, mode_dir):
    last = first + len(attempts) - 1
    stem = f"seeds_{first:06d}-{last:06d}"
    (planned / f"{stem}.attempts.json").write_text(json.dumps(attempts))
    if replayed_seeds is not None:
        episodes = [{"episode_id": i, "episode_seed": s} for i, s in enumerate(replayed_seeds)]
        (mode_dir / f"{stem}.json").write_text(json.dumps({"env_info": {}, "episodes": episodes}))


def test_chain_is_contiguous_and_outcomes_skip_unattempted_seeds(tmp_path):
    task = TaskConfig()
    gen = _Generator(task, tmp_path, attempt_timeout=10)
    gen.planned.mkdir(parents=True)
    gen.mode_dir.mkdir(parents=True)

    def attempt(seed, success, **extra):
        return {
            "seed": seed,
            "success": success,
            "seconds": 0.1,
            "error": None if success else "no path",
            **extra,
        }

    _write_batch(gen.planned, 0, [attempt(0, True), attempt(1, False), attempt(2, True)], [0], gen.mode_dir)
    crashed = [
        attempt(3, False),
        attempt(4, False, error="the worker crashed"),
        attempt(5, False, skipped=True),
    ]
    _write_batch(gen.planned, 3, crashed, None, gen.mode_dir)
    _write_batch(gen.planned, 9, [attempt(9, True)], [9], gen.mode_dir)  # after a gap: not in the chain
    chain = _planned_chain(gen.planned, 0)
    assert [(b.first, b.last) for b in chain] == [(0, 2), (3, 5)]
    assert gen.outcomes(chain) == [
        (0, True, None),
        (1, False, "no path"),
        (2, False, "the replay into the target mode failed"),
        (3, False, "no path"),
        (4, False, "the worker crashed"),
    ]
    assert _planned_chain(gen.planned, 9)[0].first == 9  # another start seed has its own chain
