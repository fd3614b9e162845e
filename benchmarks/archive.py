"""Keep a sweep's finished runs across machines: their records in git, not their checkpoints.

A benchmark grid on 2 CPU cores outlasts one session, and a session's machine (with ``runs/``) is
gone at its end. ``save`` copies, for every finished run and re-scoring under a sweep's root, the
small files a sweep reads back (``eval.json``, ``config.yaml``, ``history.json``, ``summary.json``)
into ``benchmarks/run_records/<root>``; ``restore`` puts them back under the root, so that the next
session's sweep reads those runs as done and trains only the rest. Checkpoints stay behind (70 MB
each): a restored run can no longer be re-scored under new settings, only read.

    .venv/bin/python -m benchmarks.archive save runs/bench_success
    .venv/bin/python -m benchmarks.archive restore runs/bench_success
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

__all__ = ["RECORD_FILES", "archive_dir", "restore", "save"]

#: what a sweep reads back from a finished run or re-scoring
RECORD_FILES = ("eval.json", "config.yaml", "history.json", "summary.json")
ARCHIVE = Path("benchmarks/run_records")


def archive_dir(root: Path, archive: Path = ARCHIVE) -> Path:
    """Where ``root``'s records live: the archive mirrors its path (``runs/x`` -> ``run_records/runs/x``)."""
    if root.is_absolute():
        raise ValueError(
            f"{root}: give the sweep's root relative to the repository (e.g. runs/bench_success)"
        )
    return archive / root


def _finished(root: Path) -> list[Path]:
    """Directories under ``root`` holding a finished run or re-scoring (their ``eval.json``)."""
    return sorted(p.parent for p in root.rglob("eval.json"))


def save(root: Path, archive: Path = ARCHIVE) -> list[Path]:
    """Copy the records of ``root``'s finished runs into the archive; returns the files written."""
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such sweep root")
    dest, written = archive_dir(root, archive), []
    for run_dir in _finished(root):
        for name in RECORD_FILES:
            src = run_dir / name
            if src.is_file():
                out = dest / run_dir.relative_to(root) / name
                out.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, out)
                written.append(out)
    return written


def restore(root: Path, archive: Path = ARCHIVE) -> list[Path]:
    """Copy archived records back under ``root``; a run directory that already holds an ``eval.json``
    keeps its own files (a live run is newer than its record). Returns the files written."""
    src_root = archive_dir(root, archive)
    if not src_root.is_dir():
        raise FileNotFoundError(f"{src_root}: nothing archived for {root}")
    written = []
    for record in _finished(src_root):
        run_dir = root / record.relative_to(src_root)
        if (run_dir / "eval.json").is_file():
            continue
        run_dir.mkdir(parents=True, exist_ok=True)
        for name in RECORD_FILES:
            if (record / name).is_file():
                shutil.copy2(record / name, run_dir / name)
                written.append(run_dir / name)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("action", choices=("save", "restore"))
    parser.add_argument("root", type=Path, help="the sweep's root, e.g. runs/bench_success")
    parser.add_argument("--archive", type=Path, default=ARCHIVE)
    args = parser.parse_args(argv)
    files = (save if args.action == "save" else restore)(args.root, args.archive)
    runs = {f.parent for f in files}
    print(f"{args.action}: {len(files)} files of {len(runs)} finished runs and re-scorings ({args.root})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
