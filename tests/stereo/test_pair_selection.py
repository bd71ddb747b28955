"""Frame cameras in a strip: the default AOI (areas two views see), pairs that see none of it left out with a note,
frames that do not overlap at all refused with one clear error (``geocd stereo``)."""

import json

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from synthetic import H0, Texture, dsm_local, frame_camera, render_surface

from geocd.cli import main
from geocd.errors import NoOverlapError
from geocd.io.manifest import load_manifest
from geocd.io.raster import write_image
from geocd.stereo.scene import default_aoi_grid, load_epoch_images


def _frames_dir(tmp_path, xs, *, altitude_m=60.0, k1=0.0):
    """Small nadir frames (160 × 120 px, ~96 m × 72 m on the ground) at local metres ``(x, 0)``, with a manifest
    (camera JSON beside each image, no AOI)."""
    tex = Texture(3, extent_m=200.0, step_m=0.5)
    rng = np.random.default_rng(4)
    names = []
    for i, x in enumerate(xs):
        cam = frame_camera((x, 0.0), altitude_m, width=160, height=120, focal_px=100.0, k1=k1)
        inten, _ = render_surface(cam, tex, dsm_local, H0 - 10.0, H0 + 20.0, dh=0.5)
        img = np.clip(120 + 40 * np.nan_to_num(inten) + 0.02 * rng.normal(size=inten.shape), 0, 255).astype(np.uint8)
        name = f"f{i + 1}"
        write_image(tmp_path / f"{name}.tif", img)
        (tmp_path / f"{name}.json").write_text(json.dumps(cam.to_dict()))
        names.append(name)
    m = {
        "geocd_manifest": 1,
        "name": "strip",
        "epochs": [{"name": "A", "images": [{"path": f"{n}.tif", "camera": f"{n}.json"} for n in names]}],
    }
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(m))
    return tmp_path


def test_strip_aoi_is_where_two_views_see_and_the_posting_is_finite(tmp_path):
    d = _frames_dir(tmp_path, [0.0, 40.0, 80.0, 120.0])
    m = load_manifest(d / "scene.yaml")
    images = {"A": load_epoch_images(m, m.epoch("A"))}
    info: dict = {}
    g = default_aoi_grid(m, images, params=_params(), info=info)
    l, b, r, t = g.bounds
    x0 = float(images["A"][0].camera.position[0])
    # the union of the pairwise overlaps spans the strip (f1∩f2 … f3∩f4), not the empty four-way intersection
    assert info["union"] and r - l > 100.0 and l > x0 - 10.0 and r < x0 + 130.0
    assert 0.4 <= g.posting_m <= 0.8  # ~0.6 m GSD, sampled where the frames see the ground


def _params():
    from geocd.stereo import StereoParams

    return StereoParams(height_range_m=(H0 - 10.0, H0 + 20.0))


@pytest.mark.slow
def test_strip_runs_and_skips_the_pair_that_does_not_overlap(tmp_path):
    d = _frames_dir(tmp_path, [0.0, 40.0, 80.0, 120.0])
    res = CliRunner().invoke(
        main,
        ["stereo", "--json", str(d / "scene.yaml"), "--out", str(d / "out"), "--height-range", "190", "220"],
    )
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert "A/f1__f4" not in doc["summary"]["pairs"] and "A/f1__f2" in doc["summary"]["pairs"]
    assert any("f1__f4 skipped" in n for n in doc["notes"]) and doc["summary"]["skipped_pairs"]
    assert not (d / "out" / "stereo" / "A" / "f1__f4.tif").exists()


def test_frames_far_apart_are_one_clear_error(tmp_path):
    d = _frames_dir(tmp_path, [0.0, 400.0])
    m = load_manifest(d / "scene.yaml")
    images = {"A": load_epoch_images(m, m.epoch("A"))}
    with pytest.raises(NoOverlapError, match="no two images of an epoch overlap"):
        default_aoi_grid(m, images, params=_params())
    res = CliRunner().invoke(
        main, ["stereo", str(d / "scene.yaml"), "--out", str(d / "out"), "--height-range", "0", "180"]
    )
    assert res.exit_code == 2, res.output
    assert "no two images of an epoch overlap" in res.output and "aoi.bounds" in res.output
    assert "internal error" not in res.output and "Traceback" not in res.output
