"""The documentation site (mkdocs.yml: docs/ and the API reference from the docstrings) builds with
every warning an error, as CI builds it: a docstring that griffe cannot parse, a broken link or an
API page naming a moved object fails here first."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("mkdocstrings_handlers.python", reason="the docs extra (pip install -e '.[docs]')")

ROOT = Path(__file__).resolve().parents[3]


def test_the_docs_site_builds_strictly_with_no_warning(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-5000:]
    assert "WARNING" not in out, out[-5000:]
    api = tmp_path / "site" / "api"
    # the envs package installs from envs/ (package-dir), which the build attaches under its import name
    assert 'id="l1flow_rl.envs.make_env"' in (api / "envs" / "index.html").read_text()
    assert 'id="l1flow_rl.QCLoss"' in (api / "finetune" / "index.html").read_text()
