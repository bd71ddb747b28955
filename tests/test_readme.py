"""README.md says what the code does: paths a user can run from, the bands the writers write."""

from __future__ import annotations

import re

from tests.conftest import REPO

README = REPO / "README.md"


def _code_blocks(text: str) -> list[str]:
    return re.findall(r"```[a-z]*\n(.*?)```", text, re.S)


def test_readme_examples_write_under_the_current_directory():
    """Like the CLI's default ./geocd_out/<name>: no fixed /tmp folder in an example."""
    for block in _code_blocks(README.read_text(encoding="utf-8")):
        assert "/tmp" not in block, block
