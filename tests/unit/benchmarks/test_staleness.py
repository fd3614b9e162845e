"""A published table is dated against the code that produces it: a section whose producing code
changed after its files' commits is stale and fails ``report --check``, naming it; a file that
records no commit, or a commit this clone lacks, is unverified and does not fail it."""

import json
import subprocess

from benchmarks import report
from benchmarks.report.staleness import changes_since, section_status


def _git(repo, *args):
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True, text=True).stdout.strip()


def _commit(repo, path, text, message):
    (repo / path).parent.mkdir(parents=True, exist_ok=True)
    (repo / path).write_text(text)
    _git(repo, "add", path)
    _git(repo, "commit", "-q", "-m", message)
    return _git(repo, "rev-parse", "HEAD")


def _toy() -> dict:
    """A multimodal.json (a section produced by training, evaluation and the policy)."""
    method = {"nfe": 2, "modes_hit": 2, "num_modes": 2, "share_neither": 0.01, "balance": 0.5}
    return {"steps": 100, "families": {"f": {"num_modes": 2, "methods": {"l1flow": method}}}}


def _repo(tmp_path):
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    _git(repo, "config", "user.email", "t@example.com")
    _git(repo, "config", "user.name", "t")
    first = _commit(repo, "l1flow_rl/networks/unet.py", "a = 1\n", "the network")
    return repo, first


def test_check_names_a_section_whose_producing_code_changed_after_its_commit(tmp_path, capsys):
    repo, measured = _repo(tmp_path)
    results = tmp_path / "results"
    results.mkdir()
    # one file measured in one go (its commit), one collected from a grid's runs (theirs)
    (results / "multimodal.json").write_text(json.dumps({**_toy(), "provenance": {"commit": measured}}))
    runs = {"commits": [measured], "without_commit": 0, "measured": ["2026-12-01T00:00:00+00:00"] * 2}
    success = {"quick": False, "tasks": {}, "provenance": {"runs": runs}}
    (results / "success_x.json").write_text(json.dumps(success))
    readme, doc = tmp_path / "README.md", tmp_path / "RESULTS.md"
    readme.write_text(f"{report.BEGIN}\n{report.END}\n")
    argv = ["--readme", str(readme), "--results", str(results), "--out", str(doc), "--repo", str(repo)]
    assert report.main(argv) == 0 and report.main([*argv, "--check"]) == 0
    text = doc.read_text()
    assert f"Status: current (measured: not recorded at `{measured[:12]}`" in text
    assert "Status: current (measured 2026-12-01T00:00:00+00:00" in text

    # a change elsewhere keeps them current; a change of the network makes both stale
    _commit(repo, "docs/index.md", "words\n", "docs")
    assert report.main([*argv, "--check"]) == 0
    changed = _commit(repo, "l1flow_rl/networks/unet.py", "a = 2\n", "wider UNet")
    capsys.readouterr()
    assert report.main([*argv, "--check"]) == 1
    out = capsys.readouterr().out
    stale = {line.split("'")[1]: line for line in out.splitlines() if "is stale" in line}
    assert set(stale) == {"Multi-modality (toy)", "Success and convergence, every task and method"}
    toy = stale["Multi-modality (toy)"]
    assert "is stale, its code changed since it was measured: `multimodal.json`" in toy
    assert (
        f'its code (training, evaluation, the policy) changed since, first in `{changed[:7]}` "wider UNet"'
        in toy
    )
    assert "Results-unaffected:" in out  # how to clear it without re-measuring
    assert report.main(argv) == 0
    assert "**Status: stale** (measured: not recorded at" in doc.read_text()
    assert report.main([*argv, "--check"]) == 1  # rebuilding does not clear it

    # measured again after the change: current; a later refactor that says it moves no figure
    # leaves it current
    (results / "multimodal.json").write_text(json.dumps({**_toy(), "provenance": {"commit": changed}}))
    (results / "success_x.json").unlink()
    _commit(
        repo,
        "l1flow_rl/workspace/harness.py",
        "b = 1\n",
        "split the harness\n\nResults-unaffected: a move, the same operations in the same order",
    )
    assert report.main(argv) == 0 and report.main([*argv, "--check"]) == 0


def test_files_that_cannot_be_dated_are_unverified_not_stale(tmp_path):
    repo, measured = _repo(tmp_path)
    _commit(repo, "l1flow_rl/networks/unet.py", "a = 2\n", "wider UNet")
    producers = ("the policy",)
    # no commit recorded (files saved before the scripts recorded one)
    status = section_status([("old.json", {}), ("older.json", {})], producers, repo)
    assert status.state == "unverified" and "its files record no commit" in status.line
    # a commit this clone lacks (a shallow clone), and git not there at all
    missing = {"provenance": {"commit": "0" * 40}}
    status = section_status([("shallow.json", missing)], producers, repo)
    assert status.state == "unverified" and "not in this clone's history" in status.line
    assert changes_since(tmp_path / "not_a_repo", measured, ("l1flow_rl/",)) is None
    # measured with uncommitted changes: dated by its commit, unverified where nothing changed since
    head = _git(repo, "rev-parse", "HEAD")
    status = section_status([("dirty.json", {"provenance": {"commit": f"{head}-dirty"}})], producers, repo)
    assert status.state == "unverified" and "uncommitted changes" in status.line
    # a grid's file where some runs predate the record: unverified even when its commits are current
    runs = {"provenance": {"runs": {"commits": [head], "without_commit": 2}}}
    assert section_status([("grid.json", runs)], producers, repo).state == "unverified"
    # a stale file stays stale beside undatable ones
    stale = {"provenance": {"commit": measured}}
    status = section_status([("a.json", {}), ("b.json", stale)], producers, repo)
    assert status.state == "stale" and "`b.json`" in status.reasons[0]


def test_a_merged_branch_counts_as_its_merge_commit(tmp_path):
    repo, measured = _repo(tmp_path)
    main = _git(repo, "rev-parse", "--abbrev-ref", "HEAD")
    _git(repo, "checkout", "-q", "-b", "side", measured)
    _commit(repo, "l1flow_rl/networks/unet.py", "a = 2\n", "a change on a branch, before the measurement")
    _git(repo, "checkout", "-q", main)
    measured = _commit(repo, "docs/index.md", "words\n", "the main line moves on; the table is measured here")
    paths = ("l1flow_rl/networks",)
    assert changes_since(repo, measured, paths) == []
    _git(repo, "merge", "-q", "--no-ff", "side", "-m", "Merge branch 'side'")
    # the branch's change reaches the main line with its merge: the merge is what is named
    assert [subject for _, subject in changes_since(repo, measured, paths)] == ["Merge branch 'side'"]
    _git(repo, "reset", "-q", "--hard", measured)
    _git(
        repo,
        "merge",
        "-q",
        "--no-ff",
        "side",
        "-m",
        "Merge branch 'side'\n\nResults-unaffected: checked bitwise",
    )
    assert changes_since(repo, measured, paths) == []  # its trailer speaks for the branch
