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


def test_readme_and_stereo_doc_list_every_pair_dem_band():
    """The outputs table names every band write_pair_dem writes, in its order (and their number)."""
    from geocd.stereo.products import BANDS

    rows = [line for line in README.read_text(encoding="utf-8").splitlines() if line.startswith("| `stereo/<epoch>/")]
    assert len(rows) == 1, rows
    row = rows[0]
    pos = [row.find(f"`{b}`") for b in BANDS]
    assert all(p >= 0 for p in pos), dict(zip(BANDS, pos))
    assert pos == sorted(pos), dict(zip(BANDS, pos))
    assert f"{len(BANDS)} bands" in row
    stereo_doc = (REPO / "docs" / "stereo.md").read_text(encoding="utf-8")
    out = stereo_doc[stereo_doc.index("Output per pair") :][:600]
    assert all(f"`{b}`" in out for b in BANDS), out
