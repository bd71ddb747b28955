"""The bad-input matrix of manifests, camera files and output paths: every case stops cleanly.

Same checks as test_fault_matrix.py: the exit code, one ``geocd: error:`` line naming the problem, no
traceback, no ``.part`` file, nothing new in the output folder, every input byte-identical, and (here) the
error comes fast: before any heavy work.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml


from .scenes import Cases, make_scene, run_case, write_dem_pair, write_footprints, write_rgb


@pytest.fixture(scope="module")
def fx(tmp_path_factory):
    root = tmp_path_factory.mktemp("inputs_in")
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


def _doc(fx) -> dict:
    return yaml.safe_load(fx.scene.manifest.read_text())


# --- 1. YAML ------------------------------------------------------------------------------------------------
@case("manifest: a billion-laughs alias bomb")
def _(fx, tmp):
    from tests.io.test_safe_yaml import BOMB

    m = fx.scene.root / "m_bomb.yaml"
    m.write_text(BOMB + fx.scene.manifest.read_text().replace("name: faults", "name: *i", 1))
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="expand to more than")


@case("manifest: a duplicate key")
def _(fx, tmp):
    m = fx.scene.root / "m_dupkey.yaml"
    m.write_text(fx.scene.manifest.read_text() + "name: again\n")
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="duplicate key 'name'")


# --- 2. the same image twice --------------------------------------------------------------------------------
@case("manifest: two images of an epoch with one name")
def _(fx, tmp):
    doc = _doc(fx)
    doc["epochs"][0]["images"][1]["name"] = doc["epochs"][0]["images"][0]["name"]
    m = fx.scene.root / "m_dupname.yaml"
    m.write_text(yaml.safe_dump(doc))
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="have the same image name 'A_0'")


@case("manifest: the same image file in both epochs")
def _(fx, tmp):
    doc = _doc(fx)
    doc["epochs"][1]["images"][0]["path"] = doc["epochs"][0]["images"][0]["path"]
    m = fx.scene.root / "m_dupfile.yaml"
    m.write_text(yaml.safe_dump(doc))
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="are the same file")


# --- 3. camera files ----------------------------------------------------------------------------------------
def _cam_json(fx, path: Path, **override) -> Path:
    from geocd.io.cameras import load_camera

    d = load_camera(fx.scene.root / "images" / "A_0.tif").to_dict()
    d.update(override)
    path.write_text(json.dumps(d))
    return path


def _with_camera(fx, name: str, camera: Path) -> Path:
    doc = _doc(fx)
    doc["epochs"][0]["images"][0]["camera"] = str(camera)
    m = fx.scene.root / name
    m.write_text(yaml.safe_dump(doc))
    return m


@case("ortho: --camera x.rpc.json with LAT_SCALE 1e308")
def _(fx, tmp):
    cam = _cam_json(fx, tmp / "x.rpc.json", lat_scale=1e308)
    out = tmp / "O"
    out.mkdir()
    return dict(
        args=[
            "ortho",
            fx.scene.root / "images" / "A_0.tif",
            "--dsm",
            fx.scene.root / "dem.tif",
            "--camera",
            cam,
            "--out",
            out / "x_ortho.tif",
        ],
        inputs=[cam],
        out=out,
        first="LAT_SCALE=1e+308 is outside",
    )


@case("manifest: camera: an RPC JSON with LAT_SCALE 1e308")
def _(fx, tmp):
    cam = _cam_json(fx, tmp / "x.rpc.json", lat_scale=1e308)
    return dict(
        args=["run", _with_camera(fx, "m_cam308.yaml", cam), "--out", tmp / "O"],
        inputs=[cam],
        out=tmp,
        first="LAT_SCALE=1e+308 is outside",
    )


@case("manifest: camera: an RPC text with a negative LINE_SCALE")
def _(fx, tmp):
    from .scenes import rpc_txt

    cam = rpc_txt(tmp / "neg_rpc.txt", LINE_SCALE="-60.0")
    return dict(
        args=["run", _with_camera(fx, "m_negscale.yaml", cam), "--out", tmp / "O"],
        inputs=[cam],
        out=tmp,
        first="LINE_SCALE=-60 is negative",
    )


@case("manifest: camera: a frame sidecar of width 10**400")
def _(fx, tmp):
    cam = tmp / "huge.camera.json"
    cam.write_text(
        json.dumps(
            {
                "kind": "frame",
                "crs": fx.scene.crs,
                "width": 10**400,
                "height": 100,
                "focal_px": 1000.0,
                "position": [0.0, 0.0, 1000.0],
                "opk_deg": [0.0, 0.0, 0.0],
            }
        )
    )
    return dict(
        args=["run", _with_camera(fx, "m_frame400.yaml", cam), "--out", tmp / "O"],
        inputs=[cam],
        out=tmp,
        first="'width'=1000",
    )


@case("ortho: a garbled .rpc.json sidecar next to the image")
def _(fx, tmp):
    import shutil

    img = Path(shutil.copy(fx.rgb, tmp / "photo.tif"))
    side = tmp / "photo.rpc.json"
    side.write_text('{"kind": "rpc", "line_num": [1, 2')
    return dict(
        args=["ortho", img, "--dsm", fx.a, "--out", tmp / "O" / "photo_ortho.tif"],
        inputs=[img, side],
        out=tmp,
        first="photo.rpc.json: not valid JSON",
    )


# --- 4. --out FILE names a user's own file ---------------------------------------------------------------------
def _notes(tmp: Path, name: str = "notes.txt") -> Path:
    f = tmp / name
    f.write_text("my own notes, not geocd's\n")
    return f


@case("ortho: --out names a user's text file")
def _(fx, tmp):
    f = _notes(tmp, "notes.tif")
    return dict(
        args=["ortho", fx.scene.root / "images" / "A_0.tif", "--dsm", fx.scene.root / "dem.tif", "--out", f],
        inputs=[f],
        out=tmp,
        first="exists and geocd did not write it",
    )


@case("ortho: --out names a GeoTIFF geocd ortho did not write")
def _(fx, tmp):
    import shutil

    f = Path(shutil.copy(fx.a, tmp / "mine.tif"))
    return dict(
        args=["ortho", fx.scene.root / "images" / "A_0.tif", "--dsm", fx.scene.root / "dem.tif", "--out", f],
        inputs=[f],
        out=tmp,
        first="it is not a geocd ortho GeoTIFF",
    )


@case("ortho: the status raster beside --out is a user's file")
def _(fx, tmp):
    f = _notes(tmp, "x_status.tif")
    return dict(
        args=[
            "ortho",
            fx.scene.root / "images" / "A_0.tif",
            "--dsm",
            fx.scene.root / "dem.tif",
            "--out",
            tmp / "x.tif",
        ],
        inputs=[f],
        out=tmp,
        first="x_status.tif exists and geocd did not",
    )


@case("consistency: --out names a user's text file")
def _(fx, tmp):
    f = _notes(tmp, "model.json")
    return dict(
        args=["consistency", fx.a, "--out", f], inputs=[f], out=tmp, first="it is not a geocd self-consistency model"
    )


@case("plugin-zip: --out names a user's zip")
def _(fx, tmp):
    import zipfile

    f = tmp / "photos.zip"
    with zipfile.ZipFile(f, "w") as zf:
        zf.writestr("holiday/a.jpg", b"jpeg")
    return dict(args=["plugin-zip", "--out", f], inputs=[f], out=tmp, first="it is not a geocd_qgis plugin zip")


@case("plugin-zip: a user's plugins.xml beside --out")
def _(fx, tmp):
    f = tmp / "plugins.xml"
    f.write_text('<?xml version="1.0"?>\n<plugins><pyqgis_plugin plugin_id="other"/></plugins>\n')
    return dict(
        args=["plugin-zip", "--out", tmp / "p.zip"],
        inputs=[f],
        out=tmp,
        first="plugins.xml exists and geocd did not write it",
    )


# --- 5. inputs checked before any work or output -----------------------------------------------------------
@case("run: --footprints is a raster")
def _(fx, tmp):
    out = tmp / "O"
    out.mkdir()
    return dict(
        args=["run", fx.scene.manifest, "--out", out, "--footprints", fx.rgb], out=out, first="is a raster", max_s=5.0
    )


@case("run: the manifest's footprints hold points")
def _(fx, tmp):
    import geopandas as gpd
    from shapely.geometry import Point

    pts = fx.scene.root / "points.gpkg"
    if not pts.exists():
        gpd.GeoDataFrame({"id": [1]}, geometry=[Point(0, 0)], crs=fx.scene.crs).to_file(pts)
    m = fx.scene.write("m_points.yaml", footprints="points.gpkg")
    return dict(args=["run", m, "--out", tmp / "O"], out=tmp, first="hold Point features", max_s=5.0)


@case("mpp: --change-prior is garbage with a .tif name")
def _(fx, tmp):
    g = tmp / "garbage.tif"
    g.write_bytes(bytes(range(256)) * 40)
    out = tmp / "O"
    out.mkdir()
    return dict(
        args=["mpp", fx.scene.manifest, "--out", out, "--change-prior", g],
        inputs=[g],
        out=out,
        first="garbage.tif",
        max_s=5.0,
    )


@case("mpp: --change-prior is a DEM (heights, not 0-100)")
def _(fx, tmp):
    out = tmp / "O"
    out.mkdir()
    return dict(
        args=["mpp", fx.scene.manifest, "--out", out, "--change-prior", fx.scene.root / "dem.tif"],
        out=out,
        first="it must be a 0–1 or 0–100",
        max_s=5.0,
    )


@case("synth: --supersample 0")
def _(fx, tmp):
    out = tmp / "S"
    return dict(
        args=["synth", "--tiny", "--out", out, "--supersample", "0"],
        out=tmp,
        first="0 is not a supersampling factor",
        max_s=5.0,
    )


@pytest.mark.parametrize("name", sorted(CASES))
def test_inputs_matrix(name, fx, tmp_path):
    c = CASES[name](fx, tmp_path)
    _, took = run_case(c, fx.root, tmp_path)
    assert took < c.get("max_s", 10.0), f"the error took {took:.1f} s: checked too late"
    if name.startswith("synth"):
        assert not (tmp_path / "S").exists(), "synth created its output folder before checking its options"
