"""The full run (geocd run): configuration tree, input checks, and end-to-end on simulated scenes."""

import json

import numpy as np
import pytest
import yaml

from geocd.errors import ConfigError
from geocd.io.manifest import pick_epochs
from geocd.pipeline import RunConfig, run


def test_config_round_trip(tmp_path):
    cfg = RunConfig()
    d = cfg.to_dict()
    assert d["stereo"]["window"] == 7 and d["change"]["combine"] == "majority" and d["pairs"] == "same-kind"
    p = tmp_path / "cfg.json"
    p.write_text(json.dumps(d, default=list))
    back = RunConfig.load(p)
    assert json.loads(json.dumps(back.to_dict(), default=list)) == json.loads(json.dumps(d, default=list))
    with pytest.raises(ConfigError, match="unknown run configuration keys"):
        RunConfig.from_dict({"stereo": {}, "colour": 1})
    with pytest.raises(ConfigError, match="unknown stereo parameters"):
        RunConfig.from_dict({"stereo": {"windw": 5}})


def _manifest(tmp_path, n_a, n_b):
    (tmp_path / "img").mkdir()
    eps = []
    for name, n in (("A", n_a), ("B", n_b)):
        imgs = []
        for i in range(n):
            f = tmp_path / "img" / f"{name}{i}.tif"
            f.write_bytes(b"")
            imgs.append(f"img/{f.name}")
        eps.append({"name": name, "date": f"202{len(eps)}-01-01", "images": imgs})
    p = tmp_path / "scene.yaml"
    p.write_text(yaml.safe_dump({"epochs": eps}))
    return p


def test_epoch_with_one_image_is_a_clear_error(tmp_path):
    p = _manifest(tmp_path, 3, 1)
    with pytest.raises(ConfigError, match="epoch 'B' has 1 image"):
        run(p, out_dir=tmp_path / "out")
    assert not (tmp_path / "out" / "sc_change.tif").exists()


def test_two_views_per_epoch_without_a_model_is_refused_before_any_stereo(tmp_path, sample_aoi):
    """Two images per epoch give one pair-DEM each: nothing to learn the self-consistency model from. The run
    says so before orientation and stereo (it was said after the stereo of every pair), naming the way out."""
    img = sample_aoi / "images"
    eps = [
        {"name": e, "date": d, "images": [str(img / f"{e}_sat{i}.tif") for i in (1, 2)]}
        for e, d in (("A", "2021-01-01"), ("B", "2022-01-01"))
    ]
    p = tmp_path / "scene.yaml"
    p.write_text(yaml.safe_dump({"epochs": eps}))
    with pytest.raises(ConfigError, match="no epoch has three or more images.*--model"):
        run(p, out_dir=tmp_path / "out")
    assert not (tmp_path / "out" / "stereo").exists() and not (tmp_path / "out" / "orientation").exists()


def test_pick_epochs(tmp_path):
    from geocd.io.manifest import load_manifest

    m = load_manifest(_manifest(tmp_path, 2, 2))
    a, b = pick_epochs(m)
    assert (a.name, b.name) == ("A", "B")
    with pytest.raises(ConfigError, match="two different epochs"):
        pick_epochs(m, "A", "A")


@pytest.mark.slow
def test_run_on_a_tiny_scene(tmp_path):
    import pyogrio
    import rasterio

    from geocd.synth.generate import SynthParams, generate

    scene = tmp_path / "scene"
    generate(SynthParams.tiny(seed=3, n_sat_a=3), scene)  # 3 satellite views: 3 pair-DEMs to learn from
    res = run(scene, out_dir=tmp_path / "out")
    out = res["outputs"]
    for k in ("change", "change_mask"):
        with rasterio.open(out[k]) as ds:
            assert ds.crs is not None and ds.width > 50
    layers = {n for n, _ in pyogrio.list_layers(out["changes"])}
    assert {"changes", "buildings", "curves", "layer_styles"} <= layers
    assert [n for n in layers if "build" in n] == ["buildings"]  # one building layer
    from geocd.change.building_layer import check_building_layer

    check_building_layer(pyogrio.read_dataframe(out["changes"], layer="buildings"))
    cfg = RunConfig.load(out["config"])
    assert cfg.to_dict()["region_confidence"] == 99.0
    s = json.loads(out["summary"].read_text())
    assert s["epoch_a"] == "A" and s["model"]["learned_here"]
    assert set(s["buildings"]) >= {"source", "classes", "volume_lost_m3"} and "building_damage" not in s


@pytest.mark.slow
@pytest.mark.realdata
def test_sample_aoi_end_to_end(sample_aoi, request):
    """issue 5's targets on the committed sample: building F1 ≥ 0.9 at 99%, false alarms ≲ 1% of static cells.

    ``geocd.pipeline.run(sample_aoi)``'s answer (default configuration, from scratch) is computed once per
    version of the package and scene, in the same call that makes the cached pair-DEMs the tests below use."""
    from shapely.geometry import box

    from geocd.change.buildings import score_buildings
    from geocd.change.metrics import binary_scores
    from geocd.io.raster import read_on_grid
    from geocd.io.vector import read_footprints
    from tests.sample_aoi_cache import sample_aoi_run

    res = sample_aoi_run(request.config.cache.mkdir("geocd_sample_aoi_stereo"))
    grid = res["grid"]
    truth = read_on_grid(sample_aoi / "truth" / "change_mask.tif", grid) > 0.5
    r = res["result"]
    s = binary_scores(r.changed_at(99) != 0, truth, r.observed)
    assert s["false_alarm_rate"] < 0.015, s
    assert s["recall"] > 0.45, s
    b = res["buildings"]  # epoch-A footprints (the manifest's) + new buildings detected in the change map
    assert set(b.loc[b["source"] == "footprints", "building_id"]) == set(
        read_footprints(sample_aoi / "truth" / "footprints_A.gpkg")["building_id"]
    )
    fps = read_footprints(sample_aoi / "truth" / "footprints_all.gpkg", crs=grid.crs)
    sb = score_buildings(b, fps, aoi=box(*grid.bounds))
    assert sb["f1"] >= 0.9, sb


# ------------------------------------------------------------------------------------------------
# Headline figures of sample_aoi (README, docs/self_consistency.md), pinned on cached pair-DEMs:
# everything after the stereo runs here; a mutation such as "classify buildings from the 90 % map",
# "min_changed 0.5" or "write the lowest level into the mask" fails these tests (slow: CI runs them).
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sample_pairs(request):
    from tests.sample_aoi_cache import sample_aoi_pairs

    return sample_aoi_pairs(request.config.cache.mkdir("geocd_sample_aoi_stereo"))


def _truth(m, grid, key):
    from geocd.io.raster import read_on_grid

    return read_on_grid(m.truth_path(key), grid)


def _scores(res, m, grid, level):
    from geocd.change.metrics import binary_scores

    return binary_scores(
        res.changed_at(level) == res.changed_at(level).clip(-1, 1) * (res.changed_at(level) != 0),
        _truth(m, grid, "change_mask") > 0.5,
        res.observed,
    )


def _changed(mask):
    return (mask == 1) | (mask == -1)


@pytest.fixture(scope="module")
def sample_run(sample_pairs, tmp_path_factory):
    from geocd.pipeline import run_change

    m, by, grid = sample_pairs
    return run_change(m, by, grid, out_dir=tmp_path_factory.mktemp("sc_region"))


@pytest.fixture(scope="module")
def sample_run_cell(sample_pairs, sample_run, tmp_path_factory):
    import dataclasses

    from geocd.pipeline import RunConfig, run_change

    m, by, grid = sample_pairs
    cfg = RunConfig()
    cfg = dataclasses.replace(cfg, change=dataclasses.replace(cfg.change, significance="cell"))
    # the model the region run learned on the same pair-DEMs with the same parameters (the same model)
    return run_change(m, by, grid, out_dir=tmp_path_factory.mktemp("sc_cell"), config=cfg, model=sample_run["model"])


def _building_scores(run, m, grid):
    from shapely.geometry import box

    from geocd.change.buildings import score_buildings
    from geocd.io.vector import read_footprints

    return score_buildings(
        run["buildings"], read_footprints(m.truth_path("footprints_all"), crs=grid.crs), aoi=box(*grid.bounds)
    )


@pytest.mark.slow
def test_sample_aoi_region_test_figures(sample_pairs, sample_run):
    """Cells and buildings at the reported 99 %: docs/self_consistency.md's table (region test)."""
    from geocd.change.metrics import binary_scores

    m, by, grid = sample_pairs
    res = sample_run["result"]
    assert res.significance == "region" and res.min_region_cells == 49  # one 7 x 7 matching window
    truth = _truth(m, grid, "change_mask") > 0.5
    s = binary_scores(_changed(res.changed_at(99)), truth, res.observed)
    assert s["precision"] == pytest.approx(0.791, abs=0.03), s
    assert s["recall"] == pytest.approx(0.634, abs=0.03), s
    assert s["f1"] == pytest.approx(0.704, abs=0.02), s
    assert s["false_alarm_rate"] == pytest.approx(0.0017, abs=0.0006), s
    b = _building_scores(sample_run, m, grid)
    # 4 of the 5 changed epoch-A footprints + the 3 new ones detected; demolished building 22 is missed (its
    # changed cells do not form a region significant at 99 %; the per-cell test below finds it)
    assert (b["tp"], b["fp"], b["fn"]) == (7, 0, 1), b
    bl = sample_run["buildings"]
    new = bl["source"] == "change map"
    assert new.sum() == 3 and (bl.loc[new, "class"] == "new").all()
    fr = bl.loc[bl["class"].isin(["raised", "lowered", "partly collapsed", "collapsed"]), "frac_changed"]
    assert fr.min() == pytest.approx(0.576, abs=0.05)  # the region test flags most of a changed building
    assert bl.loc[bl["class"] == "unchanged", "frac_changed"].max() < 0.05
    unobs = bl[bl["class"] == "unobserved"]
    assert len(unobs) == 9 and unobs["rule"].str.startswith("unobserved:").all()


@pytest.mark.slow
def test_sample_aoi_products_say_the_reported_level(sample_run):
    import geopandas as gpd
    import rasterio

    res = sample_run["result"]
    out = sample_run["outputs"]
    with rasterio.open(out["change_mask"]) as ds:
        assert np.array_equal(ds.read(1), res.changed_at(99))
    ch = gpd.read_file(out["changes"], layer="changes")
    assert 6 <= len(ch) <= 9 and (ch["area_m2"] >= 49 * 0.25).all()  # no polygon below the mapping unit
    assert np.isfinite(ch["volume_sigma_m3"]).all() and (ch["volume_sigma_m3"] > 0).all()
    assert (ch["confidence"] >= 99).all() and (ch["confidence"] <= 100).all()  # percent
    s = sample_run["summary"]
    # the building 31 the footprint rule calls demolished (at ground level after) is "collapsed" in the layer
    assert s["buildings"]["source"] == "footprints + change map"
    assert s["buildings"]["classes"] == {
        "collapsed": 1,
        "lowered": 1,
        "raised": 2,
        "new": 3,
        "unchanged": 23,
        "unobserved": 9,
    }
    # the collapsed and the lowered building only (556.0 m³; with every building's noise it read 1,562 m³)
    assert s["buildings"]["volume_lost_m3"] == pytest.approx(556, abs=60)


@pytest.mark.slow
def test_sample_aoi_run_writes_one_building_layer_with_the_new_buildings(sample_pairs, sample_run):
    """One building layer in the GeoPackage, in the one schema; with the manifest's epoch-A footprints it holds
    the 3 buildings built between the dates (truth ``footprints_all``, status new), found in the change map
    outside every footprint: each matches a distinct new building of the truth."""
    import geopandas as gpd
    import pyogrio

    from geocd.change.building_layer import check_building_layer
    from geocd.io.vector import read_footprints

    m, _, grid = sample_pairs
    gpkg = sample_run["outputs"]["changes"]
    names = [str(n) for n, _ in pyogrio.list_layers(gpkg)]
    assert [n for n in names if "build" in n] == ["buildings"], names
    b = gpd.read_file(gpkg, layer="buildings")
    check_building_layer(b)
    assert (b["confidence_pct"][b["class"] == "unchanged"] == 0).all()
    assert b.loc[b["class"] == "unobserved", "confidence_pct"].isna().all()
    truth = read_footprints(m.truth_path("footprints_all"), crs=grid.crs)
    truth_new = truth[truth["status"] == "new"]
    assert len(truth_new) == 3
    new = b[b["source"] == "change map"].to_crs(grid.crs)
    assert len(new) == 3 and (new["class"] == "new").all() and (new["confidence_pct"] == 99).all()
    hits = [int(truth_new.geometry.intersection(g).area.to_numpy().argmax()) for g in new.geometry]
    assert sorted(hits) == [0, 1, 2]
    for g, k in zip(new.geometry, hits):
        assert g.intersection(truth_new.geometry.iloc[k]).area > 0.5 * g.area
    assert (new["height_before_m"] < 1.0).all() and (new["height_after_m"] > 3.5).all()


@pytest.mark.slow
def test_sample_aoi_per_cell_test_figures(sample_pairs, sample_run, sample_run_cell):
    """The SRI per-cell test (significance="cell"): 90/95/99 % differ widely; buildings from the 99 % map."""
    from geocd.change.metrics import binary_scores

    m, by, grid = sample_pairs
    res = sample_run_cell["result"]
    truth = _truth(m, grid, "change_mask") > 0.5
    want = {90: (0.474, 0.0185), 95: (0.681, 0.0057), 99: (0.656, 0.0007)}
    for lev, (f1, fa) in want.items():
        s = binary_scores(_changed(res.changed_at(lev)), truth, res.observed)
        assert s["f1"] == pytest.approx(f1, abs=0.02), (lev, s)
        assert s["false_alarm_rate"] == pytest.approx(fa, abs=0.25 * fa + 0.0002), (lev, s)
    b = _building_scores(sample_run_cell, m, grid)
    assert (b["tp"], b["fp"], b["fn"]) == (8, 0, 0), b
    import rasterio

    with rasterio.open(sample_run_cell["outputs"]["change_mask"]) as ds:  # the 99 % map, not the 90 % one
        mask = ds.read(1)
    assert np.array_equal(mask, res.changed_at(99)) and _changed(res.changed_at(90)).sum() > 2 * _changed(mask).sum()
    bl = sample_run_cell["buildings"].set_index("building_id")
    # changed buildings flagged on 34 % and 37 % of their cells: min_changed 0.5 would lose them
    assert bl.loc[11, "frac_changed"] == pytest.approx(0.344, abs=0.05) and bl.loc[11, "class"] == "raised"
    # the footprint rule's "demolished" (at ground level after): "collapsed" in the building layer
    assert bl.loc[22, "frac_changed"] == pytest.approx(0.367, abs=0.05) and bl.loc[22, "class"] == "collapsed"
    assert bl.loc[31, "frac_changed"] == pytest.approx(0.512, abs=0.05) and bl.loc[31, "class"] == "collapsed"
    for bid in (11, 22, 31):  # the fraction rule classes them
        assert "≥ min_changed 15%" in bl.loc[bid, "rule"], bl.loc[bid, "rule"]
    # the changed-part rule (an option) moves no class here, in either test (docs/towns.md: nor on towns 1-3)
    from geocd.change.buildings import BuildingParams, classify_buildings
    from geocd.io.vector import read_footprints
    from geocd.stereo.surface import epoch_surface

    fa = read_footprints(m.truth_path("footprints_A"), crs=grid.crs)
    for one_run in (sample_run, sample_run_cell):
        r = one_run["result"]
        kw = dict(
            z_a=epoch_surface(by["A"]),
            z_b=epoch_surface(by["B"]),
            id_field="building_id",
            min_part_cells=r.min_region_cells,
            detect_new=False,
        )
        off = classify_buildings(fa, r.changed_at(99), r.dz_m, grid, **kw)
        on = classify_buildings(fa, r.changed_at(99), r.dz_m, grid, params=BuildingParams(changed_part=True), **kw)
        assert list(on["class"]) == list(off["class"])
        assert on["rule"].str.contains("part of").sum() == 0


def test_run_orientation_reads_a_linked_runs_orientation_folder(tmp_path):
    import json as _json

    from geocd.pipeline import run_orientation

    assert run_orientation(tmp_path, {"orientation": {"applied": False}}) == {"applied": False}
    assert run_orientation(tmp_path, {}) is None
    (tmp_path / "orientation").mkdir()
    (tmp_path / "orientation" / "orientation.json").write_text(_json.dumps({"applied": True, "reason": "ok", "x": 1}))
    assert run_orientation(tmp_path, {"orientation": None}) == {"applied": True, "reason": "ok", "corrections_px": {}}


def test_quicklook_views_are_orthos_of_each_epochs_first_image(sample_aoi):
    """The run's quick-look shows an ortho of each epoch's first image on the epoch's surface (fast: one view)."""
    from types import SimpleNamespace

    from geocd.geodesy import AOIGrid
    from geocd.io.manifest import load_manifest
    from geocd.io.raster import read_dem
    from geocd.pipeline import _quicklook_view

    m = load_manifest(sample_aoi)
    a = m.epoch("A")
    grid = AOIGrid.from_bounds(*m.aoi.bounds, m.aoi.posting_m, m.aoi.crs)
    dsm = read_dem(sample_aoi / "truth" / "dsm_A.tif", grid=grid).height_m.astype(np.float32)
    dsm[100:120, 100:120] = np.nan  # a hole: filled for the ortho
    v = _quicklook_view(m, a, grid, dsm)
    assert v.label == "ortho of A_sat1, 2023-07-18"
    assert v.image.shape == grid.shape and np.isfinite(v.image).mean() > 0.95
    # an epoch without images (a DEM standing for it) is shown by its surface
    v = _quicklook_view(m, SimpleNamespace(name="dem", images=[], date=None), grid, dsm)
    assert v.image is None and v.surface_m is dsm
