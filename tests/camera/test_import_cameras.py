"""``geocd import-cameras``: OpenSfM/ODM and orthority files → .camera.json sidecars beside the images."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from geocd.cli import main
from geocd.io.cameras import load_camera
from geocd.io.frame import read_orthority_cameras
from geocd.io.opensfm import read_opensfm_cameras
from tests.conftest import shared_data

from .test_opensfm import _reconstruction


def test_import_opensfm_writes_sidecars_beside_the_images(tmp_path):
    p, doc = _reconstruction(tmp_path)
    images = tmp_path / "images"
    images.mkdir()
    names = sorted(doc["shots"])
    for n in names[:2]:
        (images / n).write_bytes(b"")  # the images (contents not needed to read the cameras)
    res = CliRunner().invoke(main, ["--progress", "none", "import-cameras", str(p), "--image-dir", str(images)])
    assert res.exit_code == 0, res.output
    assert "not found" in res.output and names[2] in res.output  # the third image is missing: named
    cams = read_opensfm_cameras(p)
    for n in names:
        side = images / n.replace(".JPG", ".camera.json")
        assert side.is_file()
        d = json.loads(side.read_text())
        assert d["kind"] == "frame" and d["width"] == cams[n].width
        if (images / n).exists():
            np.testing.assert_allclose(load_camera(images / n, side).params, cams[n].params, atol=1e-9)
    # no overwrite asked: refuses, and leaves the sidecars as they were
    before = (images / names[0].replace(".JPG", ".camera.json")).read_text()
    res = CliRunner().invoke(main, ["import-cameras", str(p), "--image-dir", str(images), "--no-overwrite"])
    assert res.exit_code != 0 and "geocd: error:" in res.output
    assert (images / names[0].replace(".JPG", ".camera.json")).read_text() == before


def test_import_cameras_bad_inputs(tmp_path):
    res = CliRunner().invoke(main, ["import-cameras", str(tmp_path / "nope.json")])
    assert res.exit_code != 0 and "does not exist" in res.output
    (tmp_path / "x.json").write_text("{}")
    res = CliRunner().invoke(main, ["import-cameras", str(tmp_path / "x.json")])
    assert res.exit_code != 0 and "OpenSfM" in res.output


@pytest.mark.parametrize(
    "row",
    [
        'IMG_1 {x} {y} 3000 1.0 2.0 3.0 "dji FC6310 8.8mm"',  # space-separated, double quotes
        "IMG_1 {x} {y} 3000 1.0 2.0 3.0 'dji FC6310 8.8mm'",  # single quotes
        'IMG_1,{x},{y},3000,1.0,2.0,3.0,"dji FC6310 8.8mm"',  # comma-separated
        'IMG_1\t{x}\t{y}\t3000\t1.0\t2.0\t3.0\t"dji FC6310 8.8mm"',  # tabs, no header
    ],
)
def test_orthority_csv_camera_names_with_spaces(tmp_path, row):
    from .test_frame import INT_YAML, X0, Y0

    (tmp_path / "int.yaml").write_text(INT_YAML.replace("My Camera", "dji FC6310 8.8mm"))
    header = (
        ""
        if "\t" in row
        else (
            "filename x y z omega phi kappa camera\n" if "," not in row else "filename,x,y,z,omega,phi,kappa,camera\n"
        )
    )
    (tmp_path / "ext.csv").write_text(header + row.format(x=X0, y=Y0) + "\n")
    cams = read_orthority_cameras(
        tmp_path / "int.yaml", tmp_path / "ext.csv", crs="EPSG:32735", vertical_datum="ellipsoid"
    )
    assert list(cams) == ["IMG_1"] and cams["IMG_1"].focal_px == pytest.approx((1200.0, 1200.0))


@pytest.mark.realdata
def test_import_orthority_baviaans(tmp_path):
    root = shared_data("orthority_baviaans_aerial_qb2")
    res = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "import-cameras",
            str(root / "io/ngi_int_param.yaml"),
            str(root / "io/ngi_xyz_opk.csv"),
            "--vertical-datum",
            "egm2008",
            "--out",
            str(tmp_path),
        ],
    )
    assert res.exit_code == 0, res.output
    sides = sorted(tmp_path.glob("*.camera.json"))
    assert len(sides) == 4
    assert json.loads(sides[0].read_text())["width"] == 640
