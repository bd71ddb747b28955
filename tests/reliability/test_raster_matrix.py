"""The bad-DEM and non-regular-file matrix: every case stops cleanly (as test_fault_matrix.py checks it).

DEMs holding undeclared nodata sentinels, out-of-range values, centimetres, feet, an RGB photo, complex values or
unnamed extra bands are refused with the same error on the in-memory path and with ``--tiled``; a named pipe (FIFO)
given as a DEM, a manifest or an image of a manifest is refused before anything opens it (a watchdog unblocks the
pipe if something did, and the test then fails instead of hanging).
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner

from geocd.cli import main

from .scenes import Cases, error_lines, make_scene, run_case, write_dem_pair, write_rgb


@pytest.fixture(scope="module")
def fx(tmp_path_factory):
    root = tmp_path_factory.mktemp("raster_matrix_in")
    a, b = write_dem_pair(root / "dems")
    return SimpleNamespace(root=root, a=a, b=b, rgb=write_rgb(root / "dems", a), scene=make_scene(root / "scene"))


def _like_b(fx, path: Path, h: np.ndarray, **prof_changes) -> Path:
    """A GeoTIFF on DEM B's grid holding ``h`` ((rows, cols) or (bands, rows, cols)), no nodata tag by default."""
    with rasterio.open(fx.b) as ds:
        prof = {"driver": "GTiff", "width": ds.width, "height": ds.height, "crs": ds.crs, "transform": ds.transform}
    h = h if h.ndim == 3 else h[None]
    prof.update(count=h.shape[0], dtype=str(h.dtype), nodata=None)
    prof.update(prof_changes)
    units = prof.pop("units", None)
    with rasterio.open(path, "w", **prof) as dst:
        dst.write(h)
        if units:
            dst.set_band_unit(1, units)
    return path


def _b(fx) -> np.ndarray:
    with rasterio.open(fx.b) as ds:
        return ds.read(1)


def bad_sentinel(fx, tmp):
    h = _b(fx)
    h[:, ::15] = -9999.0  # 1/15 of the columns
    return _like_b(fx, tmp / "b_9999.tif", h), "-9999 in 8.3 % of its cells"


def bad_int16_sentinel(fx, tmp):
    h = np.round(_b(fx)).astype(np.int16)
    h[:5] = -32768
    return _like_b(fx, tmp / "b_int16.tif", h), "-32768 in 12 % of its cells"


def bad_inf(fx, tmp):
    h = _b(fx)
    h[np.random.default_rng(0).random(h.shape) < 0.05] = np.inf
    return _like_b(fx, tmp / "b_inf.tif", h), "of its values lie outside -11500..9500 m"


def bad_huge(fx, tmp):
    h = _b(fx)
    bad = np.random.default_rng(1).random(h.shape) < 0.5
    h[bad] = np.random.default_rng(2).uniform(1e20, 1e30, int(bad.sum()))
    return _like_b(fx, tmp / "b_huge.tif", h), "of its values lie outside -11500..9500 m"


def bad_centimetres(fx, tmp):
    return _like_b(fx, tmp / "b_cm.tif", (_b(fx) + 1500.0) * 100.0), "feet? centimetres?"


def bad_feet_unit(fx, tmp):
    return _like_b(fx, tmp / "b_ft.tif", _b(fx), units="ft"), "band unit is 'ft' (feet)"


def bad_rgb(fx, tmp):
    return fx.rgb, "is not a DEM"


def bad_complex(fx, tmp):
    return _like_b(fx, tmp / "b_complex.tif", _b(fx).astype(np.complex64)), "holds complex values"


def bad_two_bands(fx, tmp):
    h = _b(fx)
    return _like_b(fx, tmp / "b_2bands.tif", np.stack([h, h])), "is not named as heights"


BAD_DEMS = {
    f.__name__[4:]: f
    for f in (
        bad_sentinel,
        bad_int16_sentinel,
        bad_inf,
        bad_huge,
        bad_centimetres,
        bad_feet_unit,
        bad_rgb,
        bad_complex,
        bad_two_bands,
    )
}

CASES = Cases()
case = CASES.case


def _register_bad_dem(key, maker):
    for mode in ("", "--tiled"):

        @case(f"demdiff {mode or '--untiled'}: DEM B {key.replace('_', ' ')}")
        def _(fx, tmp, maker=maker, mode=mode):
            p, first = maker(fx, tmp)
            return dict(
                args=["demdiff", fx.a, p, "--out", tmp / "O", "--no-plots", *([mode] if mode else [])],
                inputs=[p],
                out=tmp,
                first=first,
            )


for _k, _m in BAD_DEMS.items():
    _register_bad_dem(_k, _m)


@case("demdiff --tiled: DEM A with -9999 columns, --tile-size 64")
def _(fx, tmp):
    h = _b(fx)
    h[:, -3:] = -9999.0
    p = _like_b(fx, tmp / "a_9999.tif", h)
    return dict(
        args=["demdiff", p, fx.b, "--out", tmp / "O", "--tile-size", "64"],
        inputs=[p],
        out=tmp,
        first="geocd demdiff: --nodata -9999",
    )


@case("demdiff: --nodata inf")
def _(fx, tmp):
    return dict(
        args=["demdiff", fx.a, fx.b, "--out", tmp / "O", "--nodata", "inf"], out=tmp, first="is not a finite number"
    )


# --- non-regular files ---------------------------------------------------------------------------------------
def _fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


@case("demdiff: DEM B is a FIFO")
def _(fx, tmp):
    return dict(
        args=["demdiff", fx.a, _fifo(tmp / "b.tif"), "--out", tmp / "O"],
        out=tmp,
        first="is a named pipe (FIFO), not a regular file",
        fifos=[tmp / "b.tif"],
    )


@case("demdiff --tiled: --base is a FIFO")
def _(fx, tmp):
    return dict(
        args=["demdiff", fx.a, fx.b, "--base", _fifo(tmp / "base.tif"), "--tiled", "--out", tmp / "O"],
        out=tmp,
        first="is a named pipe (FIFO)",
        fifos=[tmp / "base.tif"],
    )


@case("demdiff: the DEM list is a FIFO")
def _(fx, tmp):
    return dict(
        args=["demdiff", _fifo(tmp / "dems.txt"), "--out", tmp / "O"],
        out=tmp,
        first="is a named pipe (FIFO)",
        fifos=[tmp / "dems.txt"],
    )


@case("run: the manifest is a FIFO")
def _(fx, tmp):
    return dict(
        args=["run", _fifo(tmp / "scene.yaml"), "--out", tmp / "O"],
        out=tmp,
        first="is a named pipe (FIFO)",
        fifos=[tmp / "scene.yaml"],
    )


@case("change: --dem-b is a FIFO")
def _(fx, tmp):
    model = tmp / "model.json"
    model.write_text("{}")
    return dict(
        args=["change", "--dem-a", fx.a, "--dem-b", _fifo(tmp / "b.tif"), "--model", model, "--out", tmp / "O"],
        inputs=[model],
        out=tmp,
        first="--dem-b",
        fifos=[tmp / "b.tif"],
    )


@case("ortho: the DSM is a FIFO")
def _(fx, tmp):
    return dict(
        args=["ortho", fx.scene.manifest, "--dsm", _fifo(tmp / "dsm.tif"), "--out", tmp / "O"],
        out=tmp,
        first="is a named pipe (FIFO)",
        fifos=[tmp / "dsm.tif"],
    )


@case("stereo: the manifest is a FIFO")
def _(fx, tmp):
    return dict(
        args=["stereo", _fifo(tmp / "scene.yaml"), "--out", tmp / "O"],
        out=tmp,
        first="is a named pipe (FIFO)",
        fifos=[tmp / "scene.yaml"],
    )


@case("run: an image of the manifest is a FIFO")
def _(fx, tmp):
    doc = json.loads(json.dumps(fx.scene.doc))
    fifo = _fifo(tmp / "A_0.tif")
    doc["epochs"][0]["images"][0]["path"] = str(fifo)
    m = fx.scene.write("fifo_image.yaml", epochs=doc["epochs"])
    return dict(
        args=["run", m, "--out", tmp / "O"], out=tmp, first="is a named pipe (FIFO), not a regular file", fifos=[fifo]
    )


@case("run: the manifest's DEM is a FIFO")
def _(fx, tmp):
    fifo = _fifo(tmp / "dem.tif")
    m = fx.scene.write("fifo_dem.yaml", dem={"path": str(fifo), "vertical_datum": "ellipsoid"})
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="is a named pipe (FIFO)", fifos=[fifo])


@case("info: a character device")
def _(fx, tmp):
    return dict(args=["info", "/dev/zero"], out=None, first="/dev/zero is a character device, not a regular file")


def _unblock(fifos, fired):
    """Watchdog: give EOF to whatever opened a FIFO for reading (the case then fails instead of hanging)."""
    for f in fifos:
        try:
            fd = os.open(f, os.O_WRONLY | os.O_NONBLOCK)
        except OSError:  # no reader: nothing is blocked on this one
            continue
        fired.append(str(f))
        os.close(fd)


@contextlib.contextmanager
def _watchdog(fifos: list, fired: list):
    """Give EOF, after 30 s, to whatever opened one of ``fifos`` for reading (the case fails instead of hanging)."""
    dog = threading.Timer(30.0, _unblock, (fifos, fired))
    dog.start()
    try:
        yield
    finally:
        dog.cancel()


@pytest.mark.parametrize("name", sorted(CASES))
def test_raster_matrix(name, fx, tmp_path):
    c = CASES[name](fx, tmp_path)
    c.setdefault("out", tmp_path / "O")
    fired: list[str] = []
    try:
        run_case(c, fx.root, tmp_path, around=_watchdog(c.get("fifos", []), fired))
    finally:
        assert not fired, f"a FIFO was opened for reading (the command would hang): {fired}"


@pytest.mark.parametrize("key", sorted(BAD_DEMS))
def test_tiled_and_untiled_refuse_a_bad_dem_alike(key, fx, tmp_path):
    """One validation: the same error line whether the DEMs are compared in memory or tile by tile."""
    p, _ = BAD_DEMS[key](fx, tmp_path)
    lines = []
    for mode in ("--untiled", "--tiled"):
        r = CliRunner().invoke(
            main,
            [
                "--progress",
                "none",
                "demdiff",
                str(fx.a),
                str(p),
                "--out",
                str(tmp_path / mode.strip("-")),
                "--no-plots",
                mode,
            ],
        )
        assert r.exit_code == 2, r.output
        lines.append(error_lines(r.stderr))
    assert lines[0] == lines[1] and len(lines[0]) == 1, lines


def _summary(out: Path) -> dict:
    return json.loads((out / "demdiff_report.json").read_text())["summary"]


@pytest.mark.parametrize("mode", ["--untiled", "--tiled"])
@pytest.mark.slow
def test_nodata_option_makes_the_sentinel_cells_nodata(fx, tmp_path, mode):
    """--nodata -9999 on an untagged file gives what the same file with its nodata tag set gives."""
    h = _b(fx)
    h[:, ::15] = -9999.0
    untagged = _like_b(fx, tmp_path / "b_untagged.tif", h)
    tagged = _like_b(fx, tmp_path / "b_tagged.tif", h, nodata=-9999.0)
    res = {}
    for name, p, extra in (("opt", untagged, ["--nodata", "-9999"]), ("tag", tagged, [])):
        out = tmp_path / name
        r = CliRunner().invoke(
            main, ["--progress", "none", "demdiff", str(fx.a), str(p), "--out", str(out), "--no-plots", mode, *extra]
        )
        assert r.exit_code == 0, r.output
        res[name] = _summary(out)
    for k in ("n_observed", "changed_area_m2", "volume_changed_m3", "stable_nmad_m"):
        assert res["opt"][k] == res["tag"][k], k
    n_cols = h.shape[1]
    assert res["opt"]["n_observed"] <= h.size - h.shape[0] * len(range(0, n_cols, 15))
