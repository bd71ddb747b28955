"""Untrusted files: a weights or model file handed on by someone else runs no code, and a damaged one is an error.

For each case (as in test_fault_matrix.py): the exit code, one ``geocd: error:`` line naming the problem, no
traceback, no ``.part`` file, nothing new in the output folder, every input byte-identical, and no marker file
created by code hidden in the input.
"""

from __future__ import annotations

import os
import pickle
import zipfile
from pathlib import Path
from types import SimpleNamespace

import pytest
from click.testing import CliRunner

from geocd.cli import main

from .scenes import error_lines, part_files, sha256_tree, write_dem_pair


@pytest.fixture(scope="module")
def fx(tmp_path_factory):
    root = tmp_path_factory.mktemp("untrusted_in")
    a, b = write_dem_pair(root / "dems")
    return SimpleNamespace(root=root, a=a, b=b)


CASES: dict = {}


def case(name):
    def reg(fn):
        CASES[name] = fn
        return fn
    return reg


class _RunsCode:
    """Unpickling this creates ``marker`` (by os.system: what a hostile file would do)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


# --- screen: CNN weights ----------------------------------------------------------------------------------------
@case("screen: --weights .pth (zip) whose pickle runs code")
def _(fx, tmp):
    w = tmp / "evil.pth"
    with zipfile.ZipFile(w, "w") as z:
        z.writestr("archive/data.pkl", pickle.dumps({"w": _RunsCode(tmp / "pwned")}, protocol=2))
    out = tmp / "O"
    return dict(args=["screen", fx.a, fx.b, "--feature", "cnn", "--backbone", "vgg", "--weights", w, "--out", out],
                inputs=[w], out=out, first="system, which is refused without being run")


@case("screen: --weights .pth (legacy stream) whose magic number runs code")
def _(fx, tmp):
    w = tmp / "evil.pth"
    w.write_bytes(pickle.dumps(_RunsCode(tmp / "pwned"), protocol=2))
    out = tmp / "O"
    return dict(args=["screen", fx.a, fx.b, "--feature", "cnn", "--backbone", "vgg", "--weights", w, "--out", out],
                inputs=[w], out=out, first="system where a torch.save file holds plain data")


# --- landcover: joblib models ---------------------------------------------------------------------------------
@case("landcover predict: --model joblib written elsewhere that runs code")
def _(fx, tmp):
    import joblib

    model = tmp / "given.joblib"
    joblib.dump({"geocd_landcover_model": 1, "estimator": _RunsCode(tmp / "pwned")}, model)
    out = tmp / "O"
    return dict(args=["landcover", "predict", "--model", model, "--image", fx.a, "--out", out], inputs=[model],
                out=out, first="was not written by 'geocd landcover train' for this user")


@pytest.mark.parametrize("name", sorted(CASES))
def test_untrusted_matrix(name, fx, tmp_path):
    c = CASES[name](fx, tmp_path)
    watched = [fx.root, *c.get("inputs", [])]
    before = sha256_tree(watched)
    out = c.get("out")
    existing = {p for p in Path(out).rglob("*")} if out is not None and Path(out).exists() else set()
    r = CliRunner().invoke(main, ["--progress", "none", *map(str, c["args"])])
    assert not (tmp_path / "pwned").exists(), "code from an input file ran"
    assert r.exit_code == c.get("code", 2), f"exit {r.exit_code}:\n{r.output}"
    errs = error_lines(r.stderr)
    assert len(errs) == 1, r.stderr
    assert c["first"] in errs[0], errs[0]
    assert "Traceback" not in r.output
    assert not part_files(tmp_path) and not part_files(fx.root)
    assert sha256_tree(watched) == before, "an input changed"
    if out is not None and Path(out).exists():
        new = [p for p in Path(out).rglob("*") if p not in existing and p.is_file()]
        assert not new, f"files written by a failed run: {new}"
