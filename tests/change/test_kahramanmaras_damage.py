"""Real before/after: the whole example run on the Kahramanmaraş Pléiades pairs (docs/kahramanmaras.md)."""

import json

import geopandas as gpd
import numpy as np
import pytest
import rasterio

from tests.conftest import REPO, shared_data

pytestmark = [pytest.mark.realdata, pytest.mark.slow]


@pytest.fixture(scope="module")
def kahra_run(tmp_path_factory):
    shared_data("cnes_picanteo_kahramanmaras", "post_event_img2.tif")
    from geocd.pipeline import RunConfig, run

    ex = REPO / "examples" / "kahramanmaras"
    out = tmp_path_factory.mktemp("kahra")
    res = run(ex / "scene.yaml", out_dir=out, config=RunConfig(model_path=str(ex / "marseille_urban_model.json")))
    return out, res


def test_layers_and_orientation(kahra_run):
    out, res = kahra_run
    s = json.loads((out / "run_summary.json").read_text())
    assert s["orientation"]["applied"] is True
    assert s["orientation"]["after"]["cross_epoch"]["median_px"] < 0.3
    for name in (
        "sc_change.tif",
        "sc_change_mask.tif",
        "sc_changes.gpkg",
        "sc_ground_model.tif",
        "orientation/orientation.json",
        "orientation/scene.oriented.yaml",
    ):
        assert (out / name).exists(), name
    import pyogrio

    from geocd.change.building_layer import check_building_layer

    names = [str(n) for n, _ in pyogrio.list_layers(out / "sc_changes.gpkg")]
    assert [n for n in names if "build" in n] == ["buildings"], names  # one building layer, no footprints here
    dmg = gpd.read_file(out / "sc_changes.gpkg", layer="buildings")
    check_building_layer(dmg)
    assert set(dmg["source"]) == {"pre_event DSM", "post_event DSM (ground in pre_event)"}
    conf = dmg["confidence_pct"]
    assert set(conf[conf.notna()].unique()) <= {0.0, 90.0, 95.0, 99.0}
    assert conf[dmg["class"] == "unobserved"].isna().all()
    s = json.loads((out / "run_summary.json").read_text())
    assert (
        s["buildings"]["classes"] == {k: int(v) for k, v in dmg["class"].value_counts().items()}
        and "building_damage" not in s
    )


def test_headline_figures(kahra_run):
    """Measured (docs/kahramanmaras.md, the Marseille model calibrated to the pair — what `geocd run` does with a
    transferred model; the plane-residual tree rule). This fresh run, with its own stereo: 253 objects
    (pre-event objects, their building-sized changed parts cut out, + new parts of post-event objects on
    pre-event ground; 17 of them `new`), 23 collapsed, 2.3 % of the cells outside changed buildings flagged at
    99 % (without the cut: 220 objects, 14 collapsed, 3.2 %; the goal of 1 % is not met by that definition —
    93 % of those cells differ by > 3 × NMAD in CARS's DSMs too); 7.15 % of observed cells flagged at 99 % in the change mask (at 95 / 90 %:
    7.4 / 7.6 %; the docs' run: 6.9 %); the calibration fit: the pair disagrees 2.0 / 0.81 = 2.5 times more
    than the Marseille triplet on flat ground and its surfaces 0.90 m (Marseille 0.39 m) horizontally."""
    out, res = kahra_run
    from geocd.change.dsm_buildings import stable_false_alarms

    dmg = gpd.read_file(out / "sc_changes.gpkg", layer="buildings")
    cls = dmg["class"].value_counts()
    assert 240 <= len(dmg) <= 266  # 253
    assert 20 <= cls.get("collapsed", 0) <= 27  # 23
    # new buildings on pre-event ground (whole post-event objects judged by overlap found 1)
    assert 14 <= cls.get("new", 0) <= 22  # 17
    assert (dmg[dmg["class"] == "new"]["height_before_m"] < 2.5).all()
    collapsed = dmg[dmg["class"] == "collapsed"]
    assert (collapsed["height_after_m"] < collapsed["height_before_m"]).all()
    assert (collapsed["confidence_pct"] == 99.0).all()
    r = res["result"]
    cal = r.calibration
    assert cal is not None and res["summary"]["model"]["calibration"]["scale"] == pytest.approx(cal.scale, abs=1e-3)
    assert cal.scale / cal.ref_scale == pytest.approx(2.46, abs=0.35)
    assert cal.edge_sigma_m == pytest.approx(0.90, abs=0.2) and cal.ref_edge_sigma_m == pytest.approx(0.393, abs=0.01)
    flagged = float((r.changed_at(99.0) != 0)[r.observed].mean())
    assert 0.066 < flagged < 0.0745  # 0.0715; 90 % map: 0.0763
    # the mask the run wrote is the 99 % map (the one the buildings and the summary use)
    with rasterio.open(out / "sc_change_mask.tif") as ds:
        assert ds.tags()["mask_confidence_pct"] == "99"
        mask = ds.read(1)
    assert float((mask != 0)[r.observed].mean()) == pytest.approx(flagged, abs=1e-6)
    fa = stable_false_alarms(r.confidence, r.observed, dmg, res["grid"])
    assert 0.020 < fa["99"] < 0.027  # 0.0234
    assert fa["90"] > fa["99"]


def test_buildings_marked_by_eye(kahra_run):
    """docs/kahramanmaras.md, "Against buildings marked by eye": the run's layer keeps what its DSMs show. Of
    the 9 cleared, 14 new and 79 unchanged buildings of bench/data/kahramanmaras_by_eye.csv (nearest object
    within 8 m), the layer finds 9 cleared and 14 new and flags no unchanged one — as the plain rule on the same
    surfaces (median Δz within 3 m beyond ±4 m: 9, 14, 1). Before changed parts were cut out of merged objects:
    7, 12 and 1."""
    out, _ = kahra_run
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "eval_kahramanmaras_buildings", REPO / "bench" / "eval_kahramanmaras_buildings.py"
    )
    ev = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ev)
    from geocd.change.building_layer import read_building_layer

    pts = ev.read_points()
    s = ev.score_layer(pts, read_building_layer(out / "sc_changes.gpkg"))
    assert (s["cleared"]["points"], s["new"]["points"], s["unchanged"]["points"]) == (9, 14, 79)
    assert s["cleared"]["found"] == 9, s
    assert s["new"]["found"] >= 13, s  # 14
    assert s["unchanged"]["flagged"] <= 1, s  # 0
    dz, grid = ev.epoch_dz(out)
    plain = ev.score_dh(pts, dz, grid)
    assert s["cleared"]["found"] >= plain["cleared"]["found"] and s["new"]["found"] >= plain["new"]["found"] - 1


def test_the_model_as_learned_flags_twice_as_much_stable_ground(kahra_run):
    """The transfer shortfall itself: the Marseille model without the calibration (6.8 % outside changed buildings
    at 99 % on the pair-DEMs of the docs' run, plane-residual tree rule; 8.9 % with the roughness rule) — the
    calibrated test must stay well below it."""
    out, res = kahra_run
    from geocd.change.dsm_buildings import stable_false_alarms
    from geocd.consistency import ChangeParams, change_test
    from geocd.pipeline import _building_layer

    pairs = res["pairs"]
    r0 = change_test(pairs["pre_event"], pairs["post_event"], res["model"], ChangeParams(calibration="none"))
    assert r0.calibration is None
    dmg0, _ = _building_layer(
        None, r0, res["grid"], pairs["pre_event"], pairs["post_event"], res["model"], 99.0, "pre_event", "post_event"
    )
    fa0 = stable_false_alarms(r0.confidence, r0.observed, dmg0, res["grid"])["99"]
    dmg = gpd.read_file(out / "sc_changes.gpkg", layer="buildings")
    fa = stable_false_alarms(res["result"].confidence, res["result"].observed, dmg, res["grid"])["99"]
    assert 0.058 < fa0 < 0.080
    assert fa < 0.6 * fa0


def test_what_the_stable_false_alarms_are(kahra_run):
    """docs/kahramanmaras.md, "What the stable-ground false alarms at 99 % are": they lie in building
    objects the layer calls unchanged (raised or lowered parts) and in non-building objects — the trees the
    tree rule drops, felled or planted, and smaller objects —, almost none on ground. This fresh run: of 14,546
    flagged stable cells 41.1 % inside unchanged building objects, 40.1 % in tree objects of either epoch's
    DSM, 17.1 % in other non-building objects ≥ 3 m above ground in either epoch, 1.6 % on ground."""
    out, res = kahra_run
    from rasterio.features import rasterize

    from geocd.change.dsm_buildings import CHANGED, tree_cells
    from geocd.stereo.surface import epoch_surface

    r, grid, pairs = res["result"], res["grid"], res["pairs"]
    dmg = gpd.read_file(out / "sc_changes.gpkg", layer="buildings").to_crs(grid.crs)

    def mask(geoms):
        return rasterize(
            [(g, 1) for g in geoms], out_shape=grid.shape, transform=grid.transform, fill=0, dtype="uint8"
        ).astype(bool)

    flag = r.observed & ~mask(dmg[dmg["class"].isin(CHANGED)].geometry) & (np.nan_to_num(r.confidence) >= 99.0)
    allb = mask(dmg.geometry)
    za, zb = epoch_surface(pairs["pre_event"]), epoch_surface(pairs["post_event"])
    trees = tree_cells(za, grid.posting_m) | tree_cells(zb, grid.posting_m)
    with rasterio.open(out / "sc_ground_model.tif") as ds:
        dtm = ds.read(1)
    up = (za - dtm >= 3.0) | (zb - dtm >= 3.0)
    n = flag.sum()
    assert 12000 < n < 17500  # 14,546

    def share(m):
        return float((m & flag).sum() / n)

    assert 0.34 < share(allb) < 0.48  # 0.411
    assert 0.33 < share(~allb & trees) < 0.47  # 0.401
    assert 0.12 < share(~allb & ~trees & up) < 0.22  # 0.171
    assert share(~allb & ~trees & ~up) < 0.03  # 0.016: ground


def test_the_changed_part_option(kahra_run):
    """docs/kahramanmaras.md, "The changed-part rule": with it (an option), buildings holding a changed part of at
    least the mapping unit that the plane tree rule does not call a tree are changed: 2.3 % → 2.0 % of the
    stable cells flagged at 99 %, 1 → 10 partly collapsed, 622,335 → 583,684 stable cells (on the layer without
    the cut of changed parts: 3.2 % → 1.9 %, 2 → 14). By eye most of the parts it adds are felled trees and
    roadworks inside the DSM objects' outlines, so it is off by default."""
    out, res = kahra_run
    from geocd.change.dsm_buildings import DSMBuildingParams, stable_false_alarms
    from geocd.pipeline import _building_layer

    r, pairs, grid = res["result"], res["pairs"], res["grid"]
    dmg, _ = _building_layer(
        None,
        r,
        grid,
        pairs["pre_event"],
        pairs["post_event"],
        res["model"],
        99.0,
        "pre_event",
        "post_event",
        DSMBuildingParams(changed_part=True),
    )
    fa = stable_false_alarms(r.confidence, r.observed, dmg, grid)
    cls = dmg["class"].value_counts()
    assert 0.0165 < fa["99"] < 0.023  # 0.0197
    assert 8 <= cls.get("partly collapsed", 0) <= 13  # 10
    assert 550_000 < fa["stable_cells"] < 615_000  # 583,684
    assert dmg["rule"].str.contains("part of").sum() >= 8  # 10


def test_the_floor_under_the_goal(kahra_run):
    """docs/kahramanmaras.md, "The floor under the 1 % goal": of the stable cells, 1.25 % are flagged in
    non-building objects (0.95 % in tree objects) and 0.94 % in the changed parts, inside unchanged building
    objects, that were judged trees or roadworks by eye. Even a perfect building layer would leave 2.2 % (1.9 %
    counting only the trees and roadworks), so the goal of 1 % cannot be met under the issue's definition."""
    import importlib.util

    out, _ = kahra_run
    spec = importlib.util.spec_from_file_location(
        "kahramanmaras_floor", REPO / "bench" / "figures" / "kahramanmaras_floor.py"
    )
    floor = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(floor)
    f = floor.floor_figures(out)
    assert f["stable_false_alarms_99"] == pytest.approx(0.0323, abs=0.004)
    assert f["non_building_objects"] == pytest.approx(0.0125, abs=0.002)
    assert f["tree_objects"] == pytest.approx(0.0095, abs=0.002)
    assert f["by_eye_parts"]["trees or roadworks"] == pytest.approx(0.0094, abs=0.002)
    assert f["floor_tree_objects_and_by_eye_trees"] > 0.015
    assert f["floor"] > 0.018  # 0.0219: twice the goal
