"""geocd mpp on two georeferenced images: layers, styles, confidence in %, resampling and notes."""

from __future__ import annotations

import json

import numpy as np
import pyogrio
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner

from geocd.cli import main
from geocd.geodesy import AOIGrid
from geocd.io.raster import write_cog

from .scene import POSTING, make_pair


def _write(tmp_path, s):
    grid = AOIGrid("EPSG:32631", Affine(POSTING, 0, 374000.0, 0, -POSTING, 4824000.0), 200, 200)
    pa = write_cog(tmp_path / "a.tif", s["image_a"].astype(np.uint16), grid)
    # date B on a coarser, shifted grid: must be resampled onto A's
    gb = AOIGrid("EPSG:32631", Affine(0.6, 0, 373995.0, 0, -0.6, 4824004.0), 180, 180)
    from geocd.io.raster import reproject_array

    b = reproject_array(s["image_b"][0], grid, gb)
    pb = write_cog(tmp_path / "b.tif", np.nan_to_num(b, nan=0).astype(np.float32), gb)
    da = write_cog(tmp_path / "dsm_a.tif", s["dsm_a"], grid)
    db = write_cog(tmp_path / "dsm_b.tif", s["dsm_b"], grid)
    return pa, pb, da, db


@pytest.mark.slow
def test_cli_two_images(tmp_path):
    s = make_pair(0)
    pa, pb, da, db = _write(tmp_path, s)
    out = tmp_path / "out"
    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "mpp",
            "--image-a",
            str(pa),
            "--image-b",
            str(pb),
            "--dsm-a",
            str(da),
            "--dsm-b",
            str(db),
            "--out",
            str(out),
            "--max-iter",
            "60",
            "--seed",
            "2",
        ],
    )
    assert r.exit_code == 0, r.output
    assert "resampled" in r.output and "grey image" in r.output
    layers = [x[0] for x in pyogrio.list_layers(out / "mpp_buildings.gpkg")]
    assert {"buildings", "rectangles", "layer_styles"} <= set(layers)
    rects = pyogrio.read_dataframe(out / "mpp_buildings.gpkg", layer="rectangles")
    bld = pyogrio.read_dataframe(out / "mpp_buildings.gpkg", layer="buildings")
    assert len(rects) >= 4 and len(bld) >= 3
    assert rects["confidence"].between(0, 100).all() and rects["confidence"].max() > 50
    assert set(rects["change"]) <= {"unchanged", "new", "demolished"}
    assert set(bld["change"]) <= {"unchanged", "new", "demolished", "modified"}
    # the columns every building layer shares first, in its vocabulary (mpp's demolished: collapsed)
    from geocd.change.building_layer import check_building_layer

    check_building_layer(bld, shared_only=True)
    assert (bld["source"] == "A and B images").all() and list(bld.columns[4:7]) == ["area_m2", "change", "n_rectangles"]
    word = {"unchanged": "unchanged", "new": "new", "demolished": "collapsed"}
    one = bld["change"] != "modified"
    assert (bld.loc[one, "class"] == bld.loc[one, "change"].map(word)).all()
    assert rects["building_id"].isin(bld["building_id"]).all()
    with rasterio.open(out / "mpp_buildings.tif") as ds:
        cls = ds.read(1)
        assert set(np.unique(cls)) <= {0, 1, 2, 3} and (cls > 0).mean() > 0.03
    summary = json.loads((out / "mpp_summary.json").read_text())
    assert summary["method"] == "ED" and summary["thresholds"][0]["prototypes"].count("height") >= 1
    assert (out / "mpp_quicklook.png").stat().st_size > 10000
    styles = pyogrio.read_dataframe(out / "mpp_buildings.gpkg", layer="layer_styles")
    assert "categorizedSymbol" in styles["styleQML"].iloc[0]
    # the same seed gives the same rectangles
    out2 = tmp_path / "out2"
    r2 = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "mpp",
            "--image-a",
            str(pa),
            "--image-b",
            str(pb),
            "--dsm-a",
            str(da),
            "--dsm-b",
            str(db),
            "--out",
            str(out2),
            "--max-iter",
            "60",
            "--seed",
            "2",
        ],
    )
    assert r2.exit_code == 0, r2.output
    rects2 = pyogrio.read_dataframe(out2 / "mpp_buildings.gpkg", layer="rectangles")
    np.testing.assert_allclose(
        rects2[["length_m", "width_m", "orientation_deg"]].to_numpy(),
        rects[["length_m", "width_m", "orientation_deg"]].to_numpy(),
    )


def test_cli_bad_inputs(tmp_path):
    s = make_pair(0)
    pa, pb, da, db = _write(tmp_path, s)
    r = CliRunner().invoke(main, ["--progress", "none", "mpp", "--image-a", str(pa)])
    assert r.exit_code != 0 and "--image-b" in r.output
    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "mpp",
            "--image-a",
            str(pa),
            "--image-b",
            str(pb),
            "--dsm-a",
            str(da),
            "--out",
            str(tmp_path / "o"),
        ],
    )
    assert r.exit_code != 0 and "both dates" in r.output
    far = AOIGrid("EPSG:32631", Affine(POSTING, 0, 300000.0, 0, -POSTING, 4000000.0), 50, 50)
    pf = write_cog(tmp_path / "far.tif", np.ones((50, 50), np.float32), far)
    r = CliRunner().invoke(
        main, ["--progress", "none", "mpp", "--image-a", str(pa), "--image-b", str(pf), "--out", str(tmp_path / "o")]
    )
    assert r.exit_code != 0 and "overlap" in r.output


def test_a_smoothed_dsm_is_named_in_a_warning(tmp_path):
    """A DSM made with a surface median (geocd ortho's tag, or a pair-DEM's stereo parameters) is flagged: the
    height cues take their tolerances from the DSM's own noise (docs/mpp.md, "The DSM's surface median")."""
    from rasterio.transform import from_origin

    from geocd.mpp.pipeline import _warn_smoothed, dsm_smoothing

    def dsm(name, tags):
        p = tmp_path / name
        with rasterio.open(
            p,
            "w",
            driver="GTiff",
            width=4,
            height=4,
            count=1,
            dtype="float32",
            crs="EPSG:32631",
            transform=from_origin(500000, 4800000, 0.5, 0.5),
        ) as ds:
            ds.write(np.zeros((1, 4, 4), np.float32))
            ds.update_tags(**tags)
        return p

    ortho7 = dsm("ortho7.tif", {"surface_median_cells": "7"})
    ortho1 = dsm("ortho1.tif", {"surface_median_cells": "1"})
    pair_window = dsm("pair_w.tif", {"meta": json.dumps({"params": {"window": 7, "surface_median": None}})})
    pair_off = dsm("pair_1.tif", {"meta": json.dumps({"params": {"window": 7, "surface_median": 1}})})
    other = dsm("other.tif", {})
    pair_old = dsm("pair_old.tif", {"meta": json.dumps({"params": {"window": 7}})})  # before the median existed
    assert [dsm_smoothing(p) for p in (ortho7, ortho1, pair_window, pair_off, other, pair_old)] == [7, 1, 7, 1, None, 1]
    with pytest.warns(
        UserWarning, match=r"ortho7\.tif was made with a 7-cell surface median.*geocd stereo --surface-median 1"
    ):
        notes = _warn_smoothed([ortho7, ortho1, other, None])
    assert len(notes) == 1


@pytest.mark.slow
def test_the_filled_band_of_a_given_dsm_is_read(tmp_path):
    """A DSM written by geocd ortho carries a ``filled`` band (the terrain put into the stereo's holes): geocd
    mpp --dsm-a reads it onto the grid, and a DSM without one gives None. End to end, the CLI notes the roof
    hole it gave back."""
    from geocd.mpp.pipeline import _filled_band

    s = make_pair(0)
    pa, pb, da, db = _write(tmp_path, s)
    grid = AOIGrid("EPSG:32631", Affine(POSTING, 0, 374000.0, 0, -POSTING, 4824000.0), 200, 200)
    cx, cy = s["buildings"][3][:2]
    filled = np.zeros((200, 200), bool)
    filled[cy - 5 : cy + 5, cx - 4 : cx + 6] = True
    paths = []
    for k in ("a", "b"):
        h = s[f"dsm_{k}"].copy()
        h[filled] = s["ground"][filled]
        paths.append(
            write_cog(
                tmp_path / f"ortho_dsm_{k}.tif",
                {"height_m": h.astype(np.float32), "filled": filled.astype(np.float32)},
                grid,
            )
        )
    assert np.array_equal(_filled_band(paths[0], grid), filled)
    assert _filled_band(da, grid) is None
    out = tmp_path / "o"
    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "mpp",
            "--image-a",
            str(pa),
            "--image-b",
            str(pb),
            "--dsm-a",
            str(paths[0]),
            "--dsm-b",
            str(paths[1]),
            "--out",
            str(out),
            "--max-iter",
            "60",
        ],
    )
    assert r.exit_code == 0, r.output
    notes = json.loads((out / "mpp_summary.json").read_text())["notes"]
    assert any("inside raised surfaces" in n and f"{filled.sum()} cells on date A" in n for n in notes), notes


def test_the_two_rectangles_of_an_l_are_one_building():
    """The rectangle layer says which annealed object each rectangle comes from (``object_id``); the building
    layer unions the two rectangles of an L cut from one object into one L-shaped polygon of the L's area."""
    from geocd.mpp.detect import Detection
    from geocd.mpp.model import MPPResult, l_pieces
    from geocd.mpp.products import buildings_frame, rectangles_frame

    grid = AOIGrid("EPSG:32631", Affine(0.5, 0, 500000.0, 0, -0.5, 4800000.0), 200, 200)
    box = np.array([60.0, 58.0, 40.0, 30.0, 0.3])
    ell = l_pieces(box, 1.0, 1.0, 16.0, 12.0)
    rects = np.vstack([ell, [[150.0, 150.0, 20.0, 20.0, 0.0]]])
    n = len(rects)
    res = MPPResult(
        rects=rects,
        xi=np.zeros(n, np.int8),
        energy=np.full(n, -0.5),
        phi=np.full((n, 2), -0.5),
        confidence=np.full(n, 60.0),
        xi_confidence=np.full(n, 90.0),
        object_id=np.array([0, 0, 1]),
    )
    df = rectangles_frame(Detection(res, "ED", ()), grid)
    assert df["object_id"].tolist() == [0, 0, 1]
    bld = buildings_frame(df)
    assert len(bld) == 2 and (bld["class"] == "unchanged").all() and (bld["confidence_pct"] == 0).all()
    big = bld.loc[bld["n_rectangles"] == 2].iloc[0]
    # 40 × 30 cells less the 16 × 12 notch, at 0.25 m² a cell
    assert big["area_m2"] == pytest.approx((40 * 30 - 16 * 12) * 0.25, abs=0.2)
    assert big.geometry.geom_type == "Polygon" and len(big.geometry.exterior.coords) - 1 >= 6


def test_building_classes_and_confidence_in_the_shared_vocabulary():
    """mpp's labels in the building layer's words: a building only on date A is collapsed, only on date B new;
    one whose rectangles disagree is partly collapsed when a part is gone, raised when a part was added; a
    changed building's confidence_pct is its changed rectangles' label probability, an unchanged one's 0."""
    from geocd.change.building_layer import check_building_layer
    from geocd.mpp.detect import Detection
    from geocd.mpp.model import MPPResult
    from geocd.mpp.products import buildings_frame, rectangles_frame

    grid = AOIGrid("EPSG:32631", Affine(0.5, 0, 500000.0, 0, -0.5, 4800000.0), 300, 300)
    rects = np.array(
        [
            [40.0, 40.0, 20.0, 20.0, 0.0],  # unchanged
            [55.0, 40.0, 20.0, 20.0, 0.0],  # + a part gone: one building
            [150.0, 40.0, 20.0, 20.0, 0.0],  # unchanged
            [165.0, 40.0, 20.0, 20.0, 0.0],  # + a part added: one building
            [40.0, 200.0, 20.0, 20.0, 0.0],  # only on date A
            [200.0, 200.0, 20.0, 20.0, 0.0],  # only on date B
        ]
    )
    n = len(rects)
    res = MPPResult(
        rects=rects,
        xi=np.array([0, 1, 0, 2, 1, 2], np.int8),
        energy=np.full(n, -0.5),
        phi=np.full((n, 2), -0.5),
        confidence=np.full(n, 60.0),
        xi_confidence=np.array([90.0, 80.0, 90.0, 70.0, 95.0, 85.0]),
    )
    bld = buildings_frame(rectangles_frame(Detection(res, "ED", ()), grid, "pre", "post"), "pre and post images")
    check_building_layer(bld, shared_only=True)
    got = {(r["change"], r["class"], r["confidence_pct"]) for _, r in bld.iterrows()}
    assert got == {
        ("modified", "partly collapsed", 80.0),
        ("modified", "raised", 70.0),
        ("demolished", "collapsed", 95.0),
        ("new", "new", 85.0),
    }
    res.xi[:] = 0
    bld = buildings_frame(rectangles_frame(Detection(res, "ED", ()), grid))
    assert (bld["class"] == "unchanged").all() and (bld["confidence_pct"] == 0).all()
