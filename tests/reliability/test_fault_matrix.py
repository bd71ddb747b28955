"""The bad-input and fault matrix: every case stops cleanly.

For each case: the exit code, the first (and only) ``geocd: error:`` line names the problem, no traceback,
no ``.part`` file anywhere, nothing new in the output folder, and every input byte-identical (sha256 before and
after). Cases run in-process (click's runner) on tiny synthetic inputs; faults that need a second process,
a signal or a full disk are in test_output_folders.py and test_disk_full.py.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from tests.conftest import shared_data

from .scenes import Cases, make_scene, rpc_txt, run_case, write_dem_pair, write_footprints, write_rgb


@pytest.fixture(scope="module")
def fx(tmp_path_factory):
    root = tmp_path_factory.mktemp("faults_in")
    a, b = write_dem_pair(root / "dems")
    return SimpleNamespace(
        root=root,
        a=a,
        b=b,
        rgb=write_rgb(root / "dems", a),
        fp=write_footprints(root / "dems" / "footprints.gpkg", a),
        scene=make_scene(root / "scene"),
    )


CASES = Cases()
case = CASES.case


def _aoi(fx, dx=0.0, size=None, posting=1.0):
    l, b, r, t = fx.scene.aoi_bounds
    if size is not None:
        cx, cy = 0.5 * (l + r), 0.5 * (b + t)
        l, b, r, t = cx - size / 2, cy - size / 2, cx + size / 2, cy + size / 2
    return {"crs": fx.scene.crs, "bounds": [l + dx, b, r + dx, t], "posting_m": posting}


# --- 1. an input is never overwritten -------------------------------------------------------------------------
@case("run: --footprints is a product of --out")
def _(fx, tmp):
    out = tmp / "O"
    out.mkdir()
    fp = shutil.copy(fx.fp, out / "sc_changes.gpkg")
    return dict(
        args=["run", fx.scene.manifest, "--out", out, "--footprints", fp],
        inputs=[fp],
        out=out,
        first="is where this command writes its products",
    )


@case("run: --model is a product of --out")
def _(fx, tmp):
    out = tmp / "O"
    out.mkdir()
    model = out / "self_consistency_model.json"
    model.write_text("{}")
    return dict(
        args=["run", fx.scene.manifest, "--out", out, "--model", model],
        inputs=[model],
        out=out,
        first="is where this command writes its products",
    )


@case("demdiff: --footprints is a product of --out")
def _(fx, tmp):
    out = tmp / "O"
    out.mkdir()
    fp = shutil.copy(fx.fp, out / "demdiff_changes.gpkg")
    return dict(
        args=["demdiff", fx.a, fx.b, "--out", out, "--footprints", fp],
        inputs=[fp],
        out=out,
        first="is where this command writes its products",
    )


@case("demdiff: a DEM is a product of --out")
def _(fx, tmp):
    out = tmp / "O"
    out.mkdir()
    a = shutil.copy(fx.a, out / "demdiff_dh.tif")
    return dict(
        args=["demdiff", a, fx.b, "--out", out], inputs=[a], out=out, first="is where this command writes its products"
    )


@case("demdiff: a product name is a hard link to an input")
def _(fx, tmp):
    out = tmp / "O"
    out.mkdir()
    a = Path(shutil.copy(fx.a, tmp / "a.tif"))
    os.link(a, out / "demdiff_dh.tif")
    return dict(
        args=["demdiff", a, fx.b, "--out", out, "--no-plots"],
        inputs=[a, out / "demdiff_dh.tif"],
        out=out,
        first="refusing to overwrite the input file",
    )


@case("demdiff: a product name is a symlink to an input")
def _(fx, tmp):
    out = tmp / "O"
    out.mkdir()
    (out / "demdiff_dh.tif").symlink_to(fx.b)
    return dict(
        args=["demdiff", fx.a, fx.b, "--out", out, "--no-plots"],
        inputs=[],
        out=out,
        first="refusing to overwrite the input file",
    )


@case("consistency: --out is an input")
def _(fx, tmp):
    p = Path(shutil.copy(fx.a, tmp / "pair.tif"))
    return dict(args=["consistency", p, "--out", p], inputs=[p], out=None, first="would overwrite the input")


# --- 2/4. output paths -----------------------------------------------------------------------------------------
@case("demdiff: --out names an existing file")
def _(fx, tmp):
    f = tmp / "notes.txt"
    f.write_text("mine")
    return dict(args=["demdiff", fx.a, fx.b, "--out", f], inputs=[f], out=None, first="is a file")


@case("stereo: --out names an existing file")
def _(fx, tmp):
    f = tmp / "notes.txt"
    f.write_text("mine")
    return dict(args=["stereo", fx.scene.manifest, "--out", f], inputs=[f], out=None, first="is a file")


@case("demdiff: --out cannot be created (permission)")
def _(fx, tmp):
    return dict(
        args=["demdiff", fx.a, fx.b, "--out", "/sys/geocd_faults/out"],
        out=None,
        first="cannot create the output folder /sys/geocd_faults/out",
    )


@case("demdiff: --prefix escapes --out")
def _(fx, tmp):
    out = tmp / "sub" / "O"
    return dict(
        args=["demdiff", fx.a, fx.b, "--out", out, "--prefix", "../../x"],
        out=tmp,
        first="is not a plain file-name prefix",
    )


@case("probchange: --prefix escapes --out")
def _(fx, tmp):
    return dict(
        args=["probchange", fx.scene.manifest, "--out", tmp / "O", "--prefix", "../x"],
        out=tmp,
        first="is not a plain file-name prefix",
    )


# --- 4. tracebacks become messages ----------------------------------------------------------------------------
@case("manifest: text where numbers are expected in aoi.bounds")
def _(fx, tmp):
    m = fx.scene.write("m_bounds.yaml", aoi={**_aoi(fx), "bounds": ["a", 1, 2, 3]})
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="aoi.bounds[0]: expected a number, got 'a'")


@case("manifest: posting_m: fine")
def _(fx, tmp):
    m = fx.scene.write("m_posting.yaml", aoi={**_aoi(fx), "posting_m": "fine"})
    return dict(
        args=["stereo", m, "--out", tmp / "O"], out=tmp, first="aoi.posting_m: expected a number (metres), got 'fine'"
    )


@case("manifest: a binary file given as the manifest")
def _(fx, tmp):
    return dict(args=["run", fx.rgb, "--out", tmp / "O"], out=tmp, first="is not a manifest: it is a binary file")


@case("demdiff: truncated GeoTIFF")
def _(fx, tmp):
    data = Path(fx.a).read_bytes()
    p = tmp / "truncated.tif"
    p.write_bytes(data[: int(len(data) * 0.6)])
    return dict(args=["demdiff", p, fx.b, "--out", tmp / "O"], inputs=[p], out=tmp, first="truncated or corrupt")


@case("demdiff: garbage with a .tif name")
def _(fx, tmp):
    p = tmp / "garbage.tif"
    p.write_bytes(b"II*\x00" + bytes(range(256)) * 8)
    return dict(args=["demdiff", p, fx.b, "--out", tmp / "O"], inputs=[p], out=tmp, first="cannot read")


@case("demdiff: a DEM that does not exist")
def _(fx, tmp):
    return dict(args=["demdiff", tmp / "nope.tif", fx.b, "--out", tmp / "O"], out=tmp, first="does not exist")


@case("demdiff: binary list file")
def _(fx, tmp):
    p = tmp / "dems.txt"
    p.write_bytes(bytes(range(128, 256)) * 4)
    return dict(args=["demdiff", p, "--out", tmp / "O"], inputs=[p], out=tmp, first="binary or not UTF-8")


@case("run: a binary --model")
def _(fx, tmp):
    return dict(
        args=["run", fx.scene.manifest, "--out", tmp / "O", "--model", fx.rgb],
        out=tmp,
        first="is not a self-consistency model",
    )


@case("run: a binary --config")
def _(fx, tmp):
    return dict(
        args=["run", fx.scene.manifest, "--out", tmp / "O", "--config", fx.rgb], out=tmp, first="run configuration"
    )


@case("run: a 100 km AOI at 0.5 m")
def _(fx, tmp):
    m = fx.scene.write("m_huge.yaml", aoi=_aoi(fx, size=100_000.0, posting=0.5))
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="of memory")


@case("stereo: a 100 km AOI at 0.5 m")
def _(fx, tmp):
    m = fx.scene.write("m_huge2.yaml", aoi=_aoi(fx, size=100_000.0, posting=0.5))
    return dict(args=["stereo", m, "--out", tmp / "O"], out=tmp, first="of memory")


@case("demdiff --untiled: a 200000 x 200000 DEM")
def _(fx, tmp):
    import rasterio
    from rasterio.transform import from_origin

    p = tmp / "huge.tif"
    with rasterio.open(
        p,
        "w",
        driver="GTiff",
        width=200_000,
        height=200_000,
        count=1,
        dtype="float32",
        crs="EPSG:32610",
        transform=from_origin(500000, 5100000, 0.5, 0.5),
        tiled=True,
        blockxsize=1024,
        blockysize=1024,
        sparse_ok=True,
        BIGTIFF="YES",
        nodata=-9999,
    ):
        pass
    # (tiled, the default for a grid this large, reads it window by window)
    return dict(args=["demdiff", p, fx.b, "--out", tmp / "O", "--untiled"], inputs=[p], out=tmp, first="of memory")


# --- 5. implausible input is refused ----------------------------------------------------------------------------
for _name, _override, _first in (
    ("RPC latitude offset 95", {"LAT_OFF": "95.0"}, "LAT_OFF=95 is not a latitude"),
    ("RPC longitude offset 400", {"LONG_OFF": "400.0"}, "LONG_OFF=400 is not a longitude"),
    ("RPC height offset 1e308", {"HEIGHT_OFF": "1e308"}, "HEIGHT_OFF=1e+308 is not a ground height"),
    ("RPC coefficient 1e300", {"SAMP_NUM_COEFF_2": "1e300"}, "is not a plausible coefficient"),
    ("RPC non-numeric LINE_OFF", {"LINE_OFF": "abc"}, "LINE_OFF='abc' is not a number"),
    ("RPC height scale 0", {"HEIGHT_SCALE": "0"}, "height_scale is 0"),
):

    def _make(fx, tmp, _o=_override, _f=_first):
        p = rpc_txt(tmp / "cam_rpc.txt", **_o)
        return dict(args=["info", p], inputs=[p], out=None, first=_f)

    CASES[f"info: {_name}"] = _make


@case("info: NITF RPC00B with a non-numeric LINE_OFF (GDAL reads 0)")
def _(fx, tmp):
    src = shared_data("rpc_samples", "shareloc", "wv3_20.NTF")
    data = src.read_bytes()
    i = data.find(b"RPC00B") + 6 + 5  # tag, length field
    assert data[i : i + 15].startswith(b"1"), "unexpected TRE layout"
    p = tmp / "wv3_bad.NTF"
    p.write_bytes(data[: i + 15] + b"abcdef" + data[i + 21 :])
    return dict(args=["info", p], inputs=[p], out=None, first="LINE_OFF='abcdef'")


@case("demdiff: an RGB photo as a DEM")
def _(fx, tmp):
    return dict(args=["demdiff", fx.rgb, fx.b, "--out", tmp / "O"], out=tmp, first="is not a DEM")


@case("demdiff: --datum-a wgs1234")
def _(fx, tmp):
    return dict(
        args=["demdiff", fx.a, fx.b, "--out", tmp / "O", "--vertical-datum", "wgs1234"],
        out=tmp,
        first="unknown vertical datum 'wgs1234'",
    )


@case("demdiff: DEM B 100 km away from A")
def _(fx, tmp):
    import rasterio
    from rasterio.transform import Affine

    p = tmp / "far.tif"
    with rasterio.open(fx.b) as ds:
        prof, arr = ds.profile.copy(), ds.read()
    t = prof["transform"]
    prof.update(transform=Affine(t.a, t.b, t.c + 100_000, t.d, t.e, t.f), driver="GTiff")
    with rasterio.open(p, "w", **prof) as dst:
        dst.write(arr)
    return dict(args=["demdiff", fx.a, p, "--out", tmp / "O"], inputs=[p], out=tmp, first="overlap")


@case("manifest: misspelled nested keys (camra, imagez, postin_m)")
def _(fx, tmp):
    doc = yaml.safe_load(fx.scene.manifest.read_text())
    doc["aoi"]["postin_m"] = doc["aoi"].pop("posting_m")
    doc["epochs"][0]["images"][0]["camra"] = "x.json"
    doc["epochs"][1]["imagez"] = doc["epochs"][1].pop("images")
    m = fx.scene.root / "m_typos.yaml"
    m.write_text(yaml.safe_dump(doc))
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="did you mean 'posting_m'?")


@case("manifest: epochs dated out of order")
def _(fx, tmp):
    doc = yaml.safe_load(fx.scene.manifest.read_text())
    doc["epochs"][0]["date"], doc["epochs"][1]["date"] = doc["epochs"][1]["date"], doc["epochs"][0]["date"]
    m = fx.scene.root / "m_dates.yaml"
    m.write_text(yaml.safe_dump(doc))
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="is listed after 'A' (2024-06-01) but dated before")


@case("run: --epoch-a dated after --epoch-b")
def _(fx, tmp):
    return dict(
        args=["run", fx.scene.manifest, "--out", tmp / "O", "--epoch-a", "B", "--epoch-b", "A"],
        out=tmp,
        first="is dated after epoch_b",
    )


@case("run: the AOI is 100 km from the images")
def _(fx, tmp):
    m = fx.scene.write("m_far.yaml", aoi=_aoi(fx, dx=100_000.0))
    # the AOI is blamed (by the orientation step or the grid), never the DEM
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="AOI", absent="DEM")


@case("run: unknown vertical datum in the manifest")
def _(fx, tmp):
    m = fx.scene.write("m_datum.yaml", dem={"path": "dem.tif", "vertical_datum": "wgs1234"})
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="unknown vertical datum 'wgs1234'")


@pytest.mark.parametrize("name", sorted(CASES))
@pytest.mark.slow
def test_fault_matrix(name, fx, tmp_path):
    run_case(CASES[name](fx, tmp_path), fx.root, tmp_path)


def test_matrix_is_complete():
    """The issue's failures, all present (a case dropped by mistake fails here)."""
    assert len(CASES) >= 38
    text = " ".join(CASES)
    for needle in (
        "--footprints is a product",
        "existing file",
        "truncated",
        "binary --model",
        "100 km AOI",
        "latitude offset 95",
        "longitude offset 400",
        "height offset 1e308",
        "coefficient 1e300",
        "non-numeric LINE_OFF",
        "RGB photo",
        "wgs1234",
        "camra",
        "out of order",
        "--prefix escapes",
        "AOI is 100 km",
        "permission",
    ):
        assert needle in text, needle
