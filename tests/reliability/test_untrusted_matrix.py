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


from .scenes import Cases, run_case, write_dem_pair


@pytest.fixture(scope="module")
def fx(tmp_path_factory):
    root = tmp_path_factory.mktemp("untrusted_in")
    a, b = write_dem_pair(root / "dems")
    return SimpleNamespace(root=root, a=a, b=b, volume=_tiny_volume_model(root / "volume"))


def _tiny_volume_model(path: Path) -> Path:
    from geocd.volume import VolumeModel, save_model
    from tests.volume import toyscene

    return save_model(VolumeModel.create(toyscene.volume_geometry(finest_cell_m=1.0, max_depth=2), init_depth=1), path)


def _damaged_volume(fx, tmp: Path, how: str) -> Path:
    """A copy of the tiny volume model with one kind of damage (model.json kept consistent)."""
    import shutil

    import numpy as np

    p = Path(shutil.copytree(fx.volume, tmp / "model"))
    child = np.load(p / "child.npy")
    if how == "child pointers 1e8":
        np.save(p / "child.npy", np.where(child >= 0, 100_000_000, child).astype(np.int32))
    elif how == "one child pointer past the end":
        child[np.flatnonzero(child >= 0)[0]] = child.size - 2
        np.save(p / "child.npy", child)
    elif how == "truncated app.npy":
        raw = (p / "app.npy").read_bytes()
        (p / "app.npy").write_bytes(raw[: len(raw) // 2])
    return p


CASES = Cases()
case = CASES.case


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
    return dict(
        args=["screen", fx.a, fx.b, "--feature", "cnn", "--backbone", "vgg", "--weights", w, "--out", out],
        inputs=[w],
        out=out,
        first="system, which is refused without being run",
    )


@case("screen: --weights .pth (legacy stream) whose magic number runs code")
def _(fx, tmp):
    w = tmp / "evil.pth"
    w.write_bytes(pickle.dumps(_RunsCode(tmp / "pwned"), protocol=2))
    out = tmp / "O"
    return dict(
        args=["screen", fx.a, fx.b, "--feature", "cnn", "--backbone", "vgg", "--weights", w, "--out", out],
        inputs=[w],
        out=out,
        first="system where a torch.save file holds plain data",
    )


# --- landcover: joblib models ---------------------------------------------------------------------------------
@case("landcover predict: --model joblib written elsewhere that runs code")
def _(fx, tmp):
    import joblib

    model = tmp / "given.joblib"
    joblib.dump({"geocd_landcover_model": 1, "estimator": _RunsCode(tmp / "pwned")}, model)
    out = tmp / "O"
    return dict(
        args=["landcover", "predict", "--model", model, "--image", fx.a, "--out", out],
        inputs=[model],
        out=out,
        first="was not written by 'geocd landcover train' for this user",
    )


# --- volume: damaged octree models --------------------------------------------------------------------------
for _how, _file in (
    ("child pointers 1e8", "child.npy"),
    ("one child pointer past the end", "child.npy"),
    ("truncated app.npy", "app.npy"),
):

    def _render(fx, tmp, _how=_how, _file=_file):
        model, out = _damaged_volume(fx, tmp, _how), tmp / "O"
        return dict(
            args=["volume", "render", model, "--height-map", "--out", out], inputs=[model], out=out, first=_file
        )

    def _detect(fx, tmp, _how=_how, _file=_file):
        model, out = _damaged_volume(fx, tmp, _how), tmp / "O"
        return dict(args=["volume", "detect", model, fx.a, "--out", out], inputs=[model], out=out, first=_file)

    CASES[f"volume render: a model with {_how}"] = _render
    CASES[f"volume detect: a model with {_how}"] = _detect


@pytest.mark.parametrize("name", sorted(CASES))
def test_untrusted_matrix(name, fx, tmp_path):
    c = CASES[name](fx, tmp_path)
    run_case(c, fx.root, tmp_path)
    assert not (tmp_path / "pwned").exists(), "code from an input file ran"
    for p in c.get("inputs", []):  # no lock or temporary file left beside an input folder
        if Path(p).is_dir():
            assert sorted(q.name for q in Path(p).iterdir()) == sorted(q.name for q in fx.volume.iterdir())
