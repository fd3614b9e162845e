"""Whether a published table still describes today's code: each section of RESULTS.md is dated by
the commits its files were measured at, against the code that produces it.

A results file records its commits: ``provenance.runs.commits`` (a grid's runs, collected by
``bench_success`` or ``bench_ablations``: each run's own), else ``provenance.commit`` (a script that
measured in one go). A section is

- **stale** when a path that produces it (:data:`PRODUCERS`: training, evaluation, checkpoint choice,
  the policy's network and loss, ...) changed in a commit after one of its files' commits
  (``git log --first-parent <commit>..HEAD -- <paths>``: a merged branch counts as its merge commit,
  one change on the main line); ``python -m benchmarks.report --check`` fails on it, naming it;
- **unverified** when a file records no commit (saved before the scripts recorded one), was measured
  with uncommitted changes (``-dirty``), or names a commit this clone lacks (a shallow clone), or
  git is missing: it cannot be dated, so it is shown as such and does not fail ``--check``;
- **current** otherwise.

A commit that changes a producing path without moving any figure (a refactor, a comment) says so in
its message with a trailer line ``Results-unaffected: <why>``; such commits are not counted (on a
merge commit, the trailer speaks for the whole branch it brings in).
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

__all__ = [
    "PRODUCERS",
    "REPO",
    "TRAILER",
    "SectionStatus",
    "changes_since",
    "file_commits",
    "measured_range",
    "section_status",
]

#: what produces a figure, by name: the repository paths whose change may move it
PRODUCERS: dict[str, tuple[str, ...]] = {
    # the training job, its data, checkpoint choice and the config defaults it runs with
    "training": (
        "l1flow_rl/workspace/",
        "l1flow_rl/data/",
        "l1flow_rl/config/",
        "configs/config.yaml",
        "configs/train/",
        "configs/task/",
        "configs/demos/",
        "configs/policy/",
        "configs/network/",
        "configs/encoder/",
    ),
    "evaluation": ("l1flow_rl/evaluation/",),
    # the policy: its networks, losses, samplers and modules
    "the policy": ("l1flow_rl/networks/", "l1flow_rl/objectives/", "l1flow_rl/flow/", "l1flow_rl/modules/"),
    "fine-tuning": ("l1flow_rl/finetune/", "configs/finetune/"),
    "export": ("l1flow_rl/export/",),
    "the simulators": ("envs/",),
    "the experts": ("l1flow_rl/experts/",),
}
#: the repository whose history dates the files: this checkout
REPO = Path(__file__).resolve().parents[2]
#: the trailer of a commit message that declares a change of producing code without effect on figures
TRAILER = "Results-unaffected:"


@dataclass
class SectionStatus:
    """A section's state (``current``, ``stale``, ``unverified``), the line RESULTS.md shows under
    its heading, and for a stale one what changed."""

    state: str
    line: str
    reasons: list[str] = field(default_factory=list)


def file_commits(data: dict[str, Any]) -> tuple[list[str], bool]:
    """(the commits a results file was measured at, whether every figure in it records one)."""
    record = (data.get("provenance") or {}) if isinstance(data, dict) else {}
    runs = record.get("runs")
    if isinstance(runs, dict):
        commits = list(runs.get("commits") or [])
        return commits, bool(commits) and not runs.get("without_commit")
    commit = record.get("commit")
    return ([commit], True) if commit else ([], False)


def measured_range(data: dict[str, Any]) -> str | None:
    """When a file's figures were measured: its runs' first and last (a grid's), else its own time."""
    record = (data.get("provenance") or {}) if isinstance(data, dict) else {}
    runs = record.get("runs")
    if isinstance(runs, dict) and runs.get("measured"):
        first, last = runs["measured"]
        return first if first == last else f"{first} to {last}"
    return record.get("measured_at")


def _git(repo: Path, *args: str) -> str | None:
    try:
        proc = subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout if proc.returncode == 0 else None


def changes_since(repo: Path, commit: str, paths: tuple[str, ...]) -> list[tuple[str, str]] | None:
    """The commits after ``commit`` up to HEAD that change ``paths`` (oldest first, as (short hash,
    subject)), leaving out those with the :data:`TRAILER`; None when ``commit`` cannot be found in
    ``repo``'s history (a shallow clone, no git)."""
    head = _git(repo, "rev-parse", "HEAD")
    if head is None or _git(repo, "cat-file", "-e", f"{commit}^{{commit}}") is None:
        return None
    return _changes(repo, commit, head.strip(), paths)


@cache
def _changes(repo: Path, commit: str, head: str, paths: tuple[str, ...]) -> list[tuple[str, str]] | None:
    out = _git(
        repo,
        "log",
        "--first-parent",
        "--reverse",
        "--format=%h%x00%s%x00%B%x01",
        f"{commit}..{head}",
        "--",
        *paths,
    )
    if out is None:
        return None
    found = []
    for entry in out.split("\x01"):
        if not entry.strip():
            continue
        short, subject, body = entry.strip("\n").split("\x00", 2)
        if not any(line.strip().lower().startswith(TRAILER.lower()) for line in body.splitlines()):
            found.append((short, subject))
    return found


def section_status(
    files: list[tuple[str, dict[str, Any]]], producers: tuple[str, ...], repo: Path
) -> SectionStatus:
    """The state of a section made of ``files`` ((name, data)), produced by the code that
    ``producers`` (names of :data:`PRODUCERS`) name, dated in the git repository ``repo``."""
    paths = tuple(p for name in producers for p in PRODUCERS[name])
    what = ", ".join(producers)
    times = sorted(t for _, d in files if (t := measured_range(d)))
    when = (times[0] if len(set(times)) == 1 else f"{times[0]} to {times[-1]}") if times else None
    stale, unverified, commits, unrecorded = [], [], set(), []
    for name, data in files:
        found, complete = file_commits(data)
        if not found:
            unrecorded.append(name)
            continue
        if not complete:
            unverified.append(f"some runs of `{name}` record no commit")
        for commit in found:
            base = commit.removesuffix("-dirty")
            commits.add(base[:12])
            if base != commit:
                unverified.append(f"`{name}` was measured with uncommitted changes")
            changed = changes_since(repo, base, paths) if paths else []
            if changed is None:
                unverified.append(f"`{name}`: commit `{base[:12]}` is not in this clone's history")
            elif changed:
                first, subject = changed[0]
                since = f'changed since, first in `{first}` "{subject}"'
                stale.append(f"`{name}` (at `{base[:12]}`): its code ({what}) {since}")
    if unrecorded:
        many = len(unrecorded) > 1
        if len(unrecorded) == len(files):
            unverified.insert(0, f"its file{'s' * many} record{'s' * (not many)} no commit")
        else:
            names = ", ".join(f"`{n}`" for n in unrecorded)
            unverified.insert(0, f"{names} record{'s' * (not many)} no commit")
    measured = f"measured {when}" if when else "measured: not recorded"
    if commits:
        measured += " at " + ", ".join(f"`{c}`" for c in sorted(commits))
    if stale:
        return SectionStatus(
            "stale", f"**Status: stale** ({measured}): " + "; ".join(dict.fromkeys(stale)) + ".", stale
        )
    if unverified:
        shown = "; ".join(dict.fromkeys(unverified))
        return SectionStatus(
            "unverified", f"Status: unverified ({measured}): {shown}, so it cannot be dated."
        )
    return SectionStatus("current", f"Status: current ({measured}; its code ({what}) unchanged since).")
