"""The geocd CLI: info on every kind of input, and clean errors (non-zero exit, one line, no traceback)."""

import json
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from geocd.cli import main
from tests.conftest import shared_data


def run(*args):
    return CliRunner().invoke(main, list(args), catch_exceptions=False)


@pytest.fixture
def rpc_image(tmp_path):
    import rasterio

    from geocd.camera import RPCModel
    from geocd.io.raster import write_image

    src = shared_data("s2p_pleiades", "input_pair", "img_01.tif")
    with rasterio.open(src) as ds:
        model = RPCModel.from_rasterio(ds.rpcs)
    a = np.random.default_rng(0).integers(1, 2047, size=(1, 64, 64)).astype(np.uint16)
    return write_image(tmp_path / "img.tif", a, rpc=model.cropped(0, 0), nbits=11)


@pytest.mark.realdata
def test_info_rpc_image(rpc_image):
    r = run("info", str(rpc_image))
    assert r.exit_code == 0, r.output
    assert "camera: rpc" in r.output and "RPC height range" in r.output and "11-bit" in r.output
    d = json.loads(run("info", "--json", str(rpc_image)).output)
    assert d["camera"]["kind"] == "rpc" and d["camera"]["width"] == 64
    assert 0.4 < d["camera"]["gsd_m"][0] < 0.6


@pytest.mark.realdata
@pytest.mark.parametrize(
    "rel",
    [
        ("cnes_pleiades_ventoux", "left_image.tif"),
        ("rpc_samples", "rpcm", "rpc_IKONOS.txt"),
        ("rpc_samples", "shareloc", "wv3_20.NTF"),
        ("orthority_baviaans_aerial_qb2", "ngi", "dem.tif"),
        ("spacenet_atlanta_footprints", "geotiff_labels.geojson"),
    ],
)
def test_info_real_inputs(rel):
    r = run("info", "--json", str(shared_data(*rel)))
    assert r.exit_code == 0, r.output
    d = json.loads(r.output)
    assert d["type"] in ("raster", "camera", "vector")


def test_missing_file_is_a_clean_error(tmp_path):
    r = CliRunner().invoke(main, ["info", str(tmp_path / "nope.tif")])
    assert r.exit_code == 2
    assert "geocd: error:" in r.output and "does not exist" in r.output
    assert "Traceback" not in r.output


def test_garbled_rpc_file_exits_nonzero_without_traceback(tmp_path):
    p = tmp_path / "bad_rpc.txt"
    p.write_text("LINE_OFF: 12\nSAMP_OFF: banana\n")
    proc = subprocess.run([sys.executable, "-m", "geocd", "info", str(p)], capture_output=True, text=True)
    assert proc.returncode != 0
    assert "geocd: error:" in proc.stderr and "Traceback" not in proc.stderr


def test_image_without_camera_or_georeference(tmp_path):
    from geocd.errors import NoCameraError
    from geocd.io.cameras import load_camera
    from geocd.io.raster import write_image

    p = write_image(tmp_path / "plain.tif", np.ones((1, 8, 8), np.uint8))
    with pytest.raises(NoCameraError, match="no camera model"):
        load_camera(p)
    r = run("info", str(p))
    assert r.exit_code == 0 and "camera: none" in r.output


def test_json_progress_error_line(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "geocd", "--progress", "json", "info", str(tmp_path / "x.tif")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    first = json.loads(proc.stderr.splitlines()[0])
    assert first["type"] == "error" and first["error"] == "InputFileNotFoundError"
