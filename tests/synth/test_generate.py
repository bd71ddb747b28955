"""End-to-end generation of a tiny scene folder: files, manifest, RPC accuracy, determinism, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio

from geocd.errors import ConfigError, OutputError
from geocd.io.cameras import load_camera
from geocd.io.manifest import load_manifest
from geocd.synth.generate import SynthParams, generate
from geocd.synth.render import pack_scene
from geocd.synth.scene import build_town
from geocd.synth.truth import corner_check


def _read(path):
    with rasterio.open(path) as ds:
        return ds.read(), ds.tags(), ds.tags(1, "IMAGE_STRUCTURE"), ds.profile


@pytest.mark.slow
def test_scene_folder_layout_and_manifest(tiny_scene_dir, tiny_params):
    root = tiny_scene_dir.out_dir
    m = load_manifest(root)
    assert [e.name for e in m.epochs] == ["A", "B"]
    a, b = m.epoch("A"), m.epoch("B")
    assert len([i for i in a.images if "_sat" in i.name]) == tiny_params.n_sat_a
    assert len([i for i in a.images if "_air" in i.name]) == tiny_params.n_aerial
    assert len(b.images) == tiny_params.n_sat_b
    assert m.aoi.posting_m == 0.5 and m.aoi.crs.startswith("EPSG:326")
    assert m.dem.vertical_datum == "ellipsoid" and m.dem.path.exists()
    for key in ("dsm_A", "dsm_B", "dem_bare", "footprints_A", "footprints_B", "change_mask"):
        assert m.truth_path(key).exists(), key
    masks = m.truth["image_masks"]
    assert set(masks) == {i.name for e in m.epochs for i in e.images}
    for name, rel in masks.items():
        arr, tags, _, prof = _read(m.root / rel)
        cam = load_camera(next(i.path for e in m.epochs for i in e.images if i.name == name))
        assert arr.shape == (2, cam.height, cam.width) and arr.dtype == np.uint8
    # satellite: 11-bit uint16 with RPC tags; aerial: RGB uint8 with a frame sidecar
    for im in a.images + b.images:
        arr, tags, ims, prof = _read(im.path)
        cam = load_camera(im.path, im.camera)
        if "_sat" in im.name:
            assert arr.dtype == np.uint16 and arr.shape[0] == 1 and ims.get("NBITS") == "11"
            assert arr.max() <= 2047 and cam.kind == "rpc"
            lo, hi = cam.height_range()
            assert lo < float(np.nanmin(rasterio.open(m.truth_path("dem_bare")).read(1))) and hi > lo + 20
        else:
            assert arr.dtype == np.uint8 and arr.shape[0] == 3 and cam.kind == "frame"
        assert (cam.width, cam.height) == (arr.shape[2], arr.shape[1])
        assert "SUN_ELEVATION" in tags
    rep = json.loads(m.truth_path("report").read_text())
    assert rep["params"]["seed"] == tiny_params.seed
    for v in rep["views"]:
        if v["kind"] == "satellite":
            assert v["rpc_fit"]["check_max_px"] <= 0.01
            assert v["rpc_vs_physical_aoi"]["max_px"] <= 0.01
            assert 5.0 <= v["off_nadir_deg"] <= 30.0


@pytest.mark.slow
def test_truth_corners_through_written_rpcs(tiny_scene_dir, tiny_params):
    """Building corners through the RPCs read back from the GeoTIFFs land where the renderer drew them."""
    m = load_manifest(tiny_scene_dir.out_dir)
    town = build_town(tiny_params.town_params())
    from geocd.camera import camera_from_dict

    worst = 0.0
    n = 0
    for e in m.epochs:
        scene = pack_scene(town, e.name)
        for im in e.images:
            phys = camera_from_dict(json.loads((m.root / m.truth["cameras"][im.name]).read_text()))
            written = load_camera(im.path, im.camera)
            r = corner_check(town, e.name, scene, phys, written)
            if r["n_visible"]:
                worst = max(worst, r["max_px"])
                n += r["n_visible"]
    assert n > 20
    assert worst < 0.05  # Show: within 0.05 px (measured ~1e-6 px)


@pytest.mark.slow
def test_regeneration_is_deterministic(tiny_scene_dir, tiny_params, tmp_path):
    again = generate(tiny_params, tmp_path / "again")
    r1, r2 = tiny_scene_dir.out_dir, again.out_dir
    for sub in (
        "images/A_sat1.tif",
        "images/A_air1.tif",
        "images/B_sat2.tif",
        "truth/dsm_B.tif",
        "truth/change_mask.tif",
        "truth/image_masks/B_sat1.tif",
    ):
        a1, t1, _, _ = _read(r1 / sub)
        a2, t2, _, _ = _read(r2 / sub)
        np.testing.assert_array_equal(a1, a2, err_msg=sub)
    with rasterio.open(r1 / "images/A_sat1.tif") as d1, rasterio.open(r2 / "images/A_sat1.tif") as d2:
        assert d1.rpcs.to_dict() == d2.rpcs.to_dict()
    assert (r1 / "scene.yaml").read_text() == (r2 / "scene.yaml").read_text()
    import geopandas as gpd

    f1 = gpd.read_file(r1 / "truth/footprints_B.gpkg")
    f2 = gpd.read_file(r2 / "truth/footprints_B.gpkg")
    assert f1.drop(columns="geometry").equals(f2.drop(columns="geometry"))
    assert f1.geometry.geom_equals_exact(f2.geometry, 1e-9).all()


def test_variants_same_sun_and_changes(tmp_path):
    p = SynthParams.tiny(seed=2, n_sat_a=1, n_sat_b=1, n_aerial=0, same_sun=True, changes=("new", "demolished"))
    res = generate(p, tmp_path / "v")
    rep = res.report
    assert rep["sun"]["A"]["azimuth_deg"] == rep["sun"]["B"]["azimuth_deg"]
    assert {c["kind"] for c in rep["changes"]} <= {"new", "demolished", "tree_removed"}
    m = load_manifest(res.out_dir)
    assert [len(e.images) for e in m.epochs] == [1, 1] and m.truth["same_sun"] is True
    with pytest.raises(OutputError, match="not empty"):
        generate(p, tmp_path / "v")
    with pytest.raises(ConfigError):
        SynthParams(n_sat_b=0)
    with pytest.raises(ConfigError, match="ISO"):
        SynthParams(date_a="yesterday")


@pytest.mark.slow
def test_cli_tiny(tmp_path):
    from click.testing import CliRunner

    from geocd.cli import main

    out = tmp_path / "cli"
    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "synth",
            "--out",
            str(out),
            "--tiny",
            "--seed",
            "3",
            "--n-sat-a",
            "1",
            "--n-sat-b",
            "1",
            "--n-aerial",
            "1",
            "--changes",
            "new,raised",
        ],
    )
    assert r.exit_code == 0, r.output
    m = load_manifest(out)
    assert m.name == "tiny" and [len(e.images) for e in m.epochs] == [2, 1]
    rep = json.loads((out / "truth/scene_truth.json").read_text())
    assert rep["params"]["seed"] == 3 and rep["params"]["size_m"] == 64.0
    # an existing folder is refused without --overwrite, with a one-line message
    r = CliRunner().invoke(main, ["synth", "--out", str(out), "--tiny"])
    assert r.exit_code != 0 and "not empty" in r.output
    r = CliRunner().invoke(main, ["synth", "--out", str(tmp_path / "x"), "--changes", "earthquake"])
    assert r.exit_code != 0 and "unknown change types" in r.output


def test_only_views_names_must_be_views(tmp_path):
    with pytest.raises(ConfigError, match="only_views names no view"):
        generate(SynthParams.tiny(seed=1), tmp_path / "s", only_views=["A_sat1", "C_sat9"])


def test_mask_views_must_be_views(tmp_path):
    with pytest.raises(ConfigError, match="mask_views names no view"):
        generate(SynthParams.tiny(seed=1), tmp_path / "s", mask_views=["B_sat7"])


@pytest.mark.slow
def test_mask_views_writes_only_those_masks_and_the_same_ones(tmp_path, tiny_scene_dir, tiny_params):
    """``mask_views``: the other views are rendered as in a full run, only the listed views get a mask, the same."""
    out = tmp_path / "s"
    generate(tiny_params, out, only_views=["A_sat1", "B_sat1"], mask_views=["B_sat1"])
    m = load_manifest(out)
    assert set(m.truth["image_masks"]) == {"B_sat1"}
    assert not (out / "truth/image_masks/A_sat1.tif").exists()
    full = tiny_scene_dir.out_dir
    for rel in ("images/A_sat1.tif", "images/B_sat1.tif", "truth/image_masks/B_sat1.tif"):
        np.testing.assert_array_equal(_read(out / rel)[0], _read(full / rel)[0])
