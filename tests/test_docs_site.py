"""The documentation site builds with warnings as errors (mkdocs --strict: broken links, bad docstrings)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import REPO


@pytest.mark.slow
def test_mkdocs_build_strict(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if r.returncode != 0:
        print(r.stderr)
    assert r.returncode == 0, r.stderr[-4000:]
