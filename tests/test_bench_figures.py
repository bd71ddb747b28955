"""The figure registry (``python -m bench.figures``): every picture README.md and docs/ show has an entry that
makes it, ``--list`` runs, and the stamp says what made a picture."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
from pathlib import Path

import numpy as np
from PIL import Image

from bench.figures.registry import ENTRIES, by_name, pictures
from bench.figures.stamp import FOOTER_PX, is_stamped, stamp

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
#: a picture a page shows, ![caption](path.png), links to, [text](path.png), or names as docs/NAME.png
IMAGE = re.compile(r"\]\(([^)\s]+\.png)\)|\bdocs/([a-z0-9_]+\.png)")


def shown_pictures() -> dict[str, list[str]]:
    """{picture file name: pages that show it or point to it} over README.md and docs/."""
    out: dict[str, list[str]] = {}
    for page in PAGES:
        for shown, named in IMAGE.findall(page.read_text(encoding="utf-8")):
            out.setdefault(Path(shown or named).name, []).append(str(page.relative_to(REPO)))
    return out


def test_every_picture_the_docs_show_has_an_entry():
    shown = shown_pictures()
    assert len(shown) > 30  # the regular expression finds the pictures
    registered = pictures()
    assert not sorted(set(shown) - set(registered)), "pictures shown without an entry in bench/figures/registry.py"
    # and every PNG under docs/ is one of them: a picture no page shows is not kept
    files = {p.name for p in (REPO / "docs").rglob("*.png")}
    assert files == set(registered), (sorted(files - set(registered)), sorted(set(registered) - files))
    assert set(registered) <= set(shown)


def test_entries_are_well_formed():
    names = by_name()
    assert len(names) == len(ENTRIES)
    for e in ENTRIES:
        assert e.cost in ("quick", "long", "slow"), e.name
        assert e.shows and e.minutes > 0, e.name
        assert all(n in names for n in e.needs), e.name
        if e.script is not None and e.script.endswith(".py"):
            assert (REPO / e.script).is_file(), e.script
        for step in e.steps:
            assert step and all(isinstance(a, str) for a in step), e.name
    # the slow entries are left out of --quick
    assert all(e.cost != "quick" or e.minutes <= 5 for e in ENTRIES)


@pytest.mark.slow
def test_list_runs_and_names_every_entry():
    r = subprocess.run(
        [sys.executable, "-m", "bench.figures", "--list"], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr
    for e in ENTRIES:
        assert e.name in r.stdout
    assert f"{len(pictures())} pictures in {len(ENTRIES)} entries" in r.stdout


def test_dry_run_lists_the_commands_with_their_prerequisites(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "bench.figures",
            "--dry-run",
            "--work",
            str(tmp_path),
            "--only",
            "qgis_kahramanmaras.png",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    out = r.stdout
    if "skipped" not in out:  # data and QGIS present: the run, the orthos, then the picture
        assert (
            out.index("[kahramanmaras_run]") < out.index("[kahramanmaras_orthos]") < out.index("[qgis_kahramanmaras]")
        )
        assert f"{tmp_path}/kahramanmaras_run/run" in out


def test_stamp_adds_a_footer_and_the_metadata_once(tmp_path):
    p = tmp_path / "pic.png"
    Image.fromarray(np.full((40, 300, 3), 200, np.uint8)).save(p)
    assert stamp(p, command="python -m bench.figures --only x", data="sample_aoi", shows="a test", commit="abc")
    with Image.open(p) as im:
        assert im.size == (300, 40 + FOOTER_PX)
        assert im.text["geocd:command"] == "python -m bench.figures --only x" and im.text["Description"] == "a test"
        assert im.text["geocd:data"] == "sample_aoi" and len(im.text["Creation Time"]) == 10
        footer = np.asarray(im.convert("RGB"))[40:]
        assert (footer < 200).any()  # the grey text is there
    assert is_stamped(p)
    assert not stamp(p, command="again", data="", shows="")  # a stamped picture is left alone
    with Image.open(p) as im:
        assert im.size == (300, 40 + FOOTER_PX)


def test_the_pictures_page_names_every_entry():
    page = (REPO / "docs" / "reference" / "figures.md").read_text(encoding="utf-8")
    for e in ENTRIES:
        assert f"| `{e.name}` |" in page, e.name
        for p in e.pictures:
            assert f"`{p}`" in page, p
