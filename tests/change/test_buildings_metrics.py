import numpy as np
import pytest
from shapely.geometry import box

from geocd.change.buildings import building_scores, classify_buildings
from geocd.change.metrics import best_threshold_f1, binary_scores, roc_curve
from geocd.change.building_layer import buildings_qml
from geocd.change.styles import categorized_polygon_qml
from geocd.geodesy import AOIGrid


@pytest.fixture
def grid():
    return AOIGrid.from_bounds(500000, 4000000, 500060, 4000060, 0.5, "EPSG:32631")


def test_classify_buildings(grid):
    import geopandas as gpd

    l, b, r, t = grid.bounds
    fps = gpd.GeoDataFrame(
        {"bid": [1, 2, 3, 4, 5]},
        geometry=[
            box(l + 2, b + 2, l + 12, b + 12),  # new: ground in A, +8 m in B
            box(l + 20, b + 2, l + 30, b + 12),  # demolished: 9 m in A, ground in B
            box(l + 40, b + 2, l + 50, b + 12),  # raised: 6 m → 9 m
            box(l + 2, b + 30, l + 12, b + 40),  # unchanged 6 m
            box(l + 30, b + 30, l + 40, b + 40),  # unobserved
        ],
        crs=grid.crs,
    )
    from geocd.io.vector import polygons_to_mask

    def burn(i):
        return polygons_to_mask(fps.iloc[[i]], grid).astype(bool)

    za = np.zeros(grid.shape, np.float32)
    zb = np.zeros(grid.shape, np.float32)
    zb[burn(0)] = 8
    za[burn(1)] = 9
    za[burn(2)] = 6
    zb[burn(2)] = 9
    za[burn(3)] = 6
    zb[burn(3)] = 6
    dz = zb - za
    mask = np.sign(dz).astype(np.int8)
    mask[burn(4)] = -128
    out = classify_buildings(fps, mask, dz, grid, z_a=za, z_b=zb, id_field="bid")
    assert list(out["class"]) == ["new", "demolished", "raised", "unchanged", "unobserved"]
    assert out.loc[0, "mean_dz_m"] == pytest.approx(8, abs=1e-5)
    assert out.loc[0, "volume_m3"] == pytest.approx(8 * 100, rel=0.05)
    assert list(out["building_id"]) == [1, 2, 3, 4, 5]
    s = building_scores(out["class"], ["new", "demolished", "raised", "unchanged", "unchanged"])
    assert s["f1"] == 1.0 and s["class_accuracy_on_changed"] == 1.0


def test_binary_scores_and_roc():
    truth = np.zeros((10, 10), bool)
    truth[:3] = True
    pred = truth.copy()
    pred[5, 5] = True
    s = binary_scores(pred, truth)
    assert s["tp"] == 30 and s["fp"] == 1 and s["fn"] == 0
    assert s["false_alarm_rate"] == pytest.approx(1 / 70)
    rng = np.random.default_rng(0)
    score = truth + rng.normal(scale=0.3, size=truth.shape)
    fpr, tpr, thr, auc = roc_curve(score, truth)
    assert 0.95 < auc <= 1.0 and fpr[0] == 0 and tpr[-1] == 1
    best, sc = best_threshold_f1(score, truth)
    assert sc["f1"] > 0.9


def test_qml_is_well_formed_xml():
    import xml.etree.ElementTree as ET

    for q in (buildings_qml(), categorized_polygon_qml("sign", {1: ("#ff0000", "raised"), -1: ("#0000ff", "lowered")})):
        root = ET.fromstring(q.split("\n", 1)[1])
        r = root.find("renderer-v2")
        assert r.get("type") == "categorizedSymbol"
        assert len(r.find("categories")) == len(r.find("symbols"))


def test_unobserved_building_from_a_change_result_says_why(grid):
    """A footprint on cells no comparison saw is `unobserved` (not `unchanged`), with the rule in words."""
    import geopandas as gpd

    from geocd.consistency import change_test, learn_self_consistency
    from tests.test_consistency import Rec

    rng = np.random.default_rng(5)
    shape = grid.shape
    l, b, r, t = grid.bounds

    def rec(name, hide=None):
        z = rng.normal(scale=0.2, size=shape).astype(np.float32)
        valid = np.ones(shape, bool)
        if hide is not None:
            valid[hide] = False
        return Rec(
            np.where(valid, z, np.nan).astype(np.float32),
            rng.uniform(0, 1, shape).astype(np.float32),
            np.ones(shape, np.float32),
            valid,
            grid,
            name,
        )

    hide = (slice(10, 50), slice(10, 50))  # rows 10..49, cols 10..49: x l+5..l+25, y t-25..t-5
    A = [rec(f"A{i}") for i in range(3)]
    B = [rec(f"B{i}", hide) for i in range(3)]
    res = change_test(A, B, learn_self_consistency([A]))
    fps = gpd.GeoDataFrame(
        {"building_id": [1, 2, 3]},
        geometry=[
            box(l + 8, t - 22, l + 22, t - 8),  # entirely in the hole
            box(l + 20, t - 22, l + 34, t - 8),  # 5/14 of it in the hole: observed on 64%
            box(l + 40, b + 5, l + 50, b + 15),
        ],  # fully observed
        crs=grid.crs,
    )
    out = classify_buildings(fps, res.changed_at(99), res.dz_m, grid, id_field="building_id", confidence_level=99)
    assert list(out["class"]) == ["unobserved", "unchanged", "unchanged"]
    assert out.loc[0, "frac_observed"] == 0.0 and "min_observed" in out.loc[0, "rule"]
    assert out.loc[1, "frac_observed"] == pytest.approx(9 / 14, abs=0.05)
    assert out.loc[2, "frac_observed"] == pytest.approx(1.0) and out.loc[2, "rule"].startswith("unchanged")
    # 60 % outside the grid: unobserved by the AOI rule, and frac_observed counts the part off the grid
    half = gpd.GeoDataFrame({"building_id": [9]}, geometry=[box(r - 4, b + 5, r + 6, b + 15)], crs=grid.crs)
    o = classify_buildings(half, res.changed_at(99), res.dz_m, grid, id_field="building_id")
    assert o.loc[0, "class"] == "unobserved" and "min_inside" in o.loc[0, "rule"]
    assert o.loc[0, "frac_observed"] == pytest.approx(0.4, abs=0.05)


def test_new_buildings_come_from_detection_not_from_footprints(grid):
    """Epoch-A footprints only: a building raised on bare ground outside them is found as a `new` candidate;
    a small raised blob (below min_changed × the median footprint) and a car-high one are not."""
    import geopandas as gpd

    from geocd.change.buildings import score_buildings
    from geocd.io.vector import polygons_to_mask

    l, b, r, t = grid.bounds
    known = gpd.GeoDataFrame(
        {"building_id": [1, 2]},
        geometry=[box(l + 2, b + 2, l + 12, b + 12), box(l + 20, b + 2, l + 30, b + 12)],
        crs=grid.crs,
    )
    za = np.zeros(grid.shape, np.float32)
    za[polygons_to_mask(known, grid).astype(bool)] = 6.0
    zb = za.copy()
    new_fp = box(l + 35, b + 35, l + 47, b + 45)  # 120 m², built between the dates
    blob = box(l + 5, t - 8, l + 7, t - 6)  # 4 m² < 0.15 × median footprint (15 m²)
    car = box(l + 30, t - 12, l + 35, t - 7)  # 25 m² but raised by 1.2 m only
    for g, h in ((new_fp, 9.0), (blob, 5.0), (car, 1.2)):
        zb[polygons_to_mask(gpd.GeoDataFrame(geometry=[g], crs=grid.crs), grid).astype(bool)] = h
    dz = zb - za
    mask = np.where(np.abs(dz) > 1.0, np.sign(dz), 0).astype(np.int8)
    out = classify_buildings(known, mask, dz, grid, z_a=za, z_b=zb, id_field="building_id", confidence_level=99)
    det = out[out["source"] == "change map"]
    assert len(det) == 1 and det.iloc[0]["class"] == "new" and det.iloc[0]["building_id"] == -1
    assert (
        det.iloc[0].geometry.area == pytest.approx(120, rel=0.05) and "outside every footprint" in det.iloc[0]["rule"]
    )
    assert list(out.loc[out["source"] == "footprints", "class"]) == ["unchanged", "unchanged"]
    truth = gpd.GeoDataFrame(
        {"building_id": [1, 2, 3], "status": ["unchanged", "unchanged", "new"]},
        geometry=[*known.geometry, new_fp],
        crs=grid.crs,
    )
    s = score_buildings(out, truth, aoi=box(*grid.bounds))
    assert (s["tp"], s["fp"], s["fn"], s["f1"]) == (1, 0, 0, 1.0)
    # not detected → the new building is a false negative, not silently absent from the score
    s0 = score_buildings(out[out["source"] == "footprints"], truth, aoi=box(*grid.bounds))
    assert (s0["tp"], s0["fn"]) == (0, 1)
    none = classify_buildings(known, mask, dz, grid, z_a=za, z_b=zb, id_field="building_id", detect_new=False)
    assert (none["source"] == "footprints").all()


def test_a_building_with_a_changed_part_is_changed(grid):
    """With ``changed_part`` (an option), a connected changed part of at least the map's mapping unit makes a
    building changed, whatever its changed fraction; the same number of scattered cells, or a part below the
    unit, does not."""
    import geopandas as gpd

    l, b, r, t = grid.bounds
    fps = gpd.GeoDataFrame(
        geometry=[
            box(l + 2, b + 2, l + 22, b + 22),  # a 4 × 4 m part lowered
            box(l + 30, b + 2, l + 50, b + 22),  # 64 scattered lowered cells
            box(l + 2, b + 30, l + 22, b + 50),  # a 3 × 3 m part raised
            box(l + 30, b + 30, l + 50, b + 50),
        ],  # nothing
        crs=grid.crs,
    )
    from geocd.io.vector import polygons_to_mask

    z = np.where(polygons_to_mask(fps, grid).astype(bool), 9.0, 0.0).astype(np.float32)  # 9 m blocks
    mask = np.zeros(grid.shape, np.int8)
    # footprints in rows/cols (0.5 m cells, north up): building 0 spans rows 76–115, cols 4–43
    mask[80:88, 10:18] = -1  # 64 cells = 16 m², 4 % of 1600
    mask[80:112:4, 64:96:4] = -1  # 8 × 8 = 64 isolated cells
    mask[30:36, 10:16] = 1  # 36 cells
    dz = mask.astype(np.float32) * 3.0
    from geocd.change.buildings import BuildingParams

    on = BuildingParams(changed_part=True)
    out = classify_buildings(fps, mask, dz, grid, z_a=z, z_b=z + dz, min_part_cells=49, params=on)
    assert list(out["class"]) == ["lowered", "unchanged", "unchanged", "unchanged"]
    assert "part of 64 cells" in out.loc[0, "rule"]
    assert out.loc[0, "frac_changed"] == pytest.approx(0.04)
    out = classify_buildings(fps, mask, dz, grid, z_a=z, z_b=z + dz, min_part_cells=36, params=on)
    assert list(out["class"]) == ["lowered", "unchanged", "raised", "unchanged"]
    # the fraction rule alone: the default (the rule is an option), or no mapping unit given
    for kw in ({"min_part_cells": 36}, {"params": on}):
        out = classify_buildings(fps, mask, dz, grid, z_a=z, z_b=z + dz, **kw)
        assert list(out["class"]) == ["unchanged"] * 4


def test_largest_parts_matches_a_brute_force_count():
    from scipy import ndimage

    from geocd.change.buildings import largest_parts

    rng = np.random.default_rng(4)
    labels = np.zeros((60, 80), np.int32)
    labels[5:30, 5:40] = 1
    labels[5:30, 40:75] = 2  # touches building 1
    labels[35:55, 10:30] = 3
    cm = rng.choice(np.array([-1, 0, 1], np.int8), size=labels.shape, p=[0.25, 0.45, 0.3])
    cm[0, 0] = -128
    cells, sign = largest_parts(cm, labels, 4)
    for k in (1, 2, 3):
        best, bs = 0, 0
        for s in (1, -1):
            lab, n = ndimage.label((labels == k) & (cm == s), structure=np.ones((3, 3), bool))
            m = max((int((lab == j).sum()) for j in range(1, n + 1)), default=0)
            if m > best:
                best, bs = m, s
        assert (cells[k - 1], sign[k - 1]) == (best, bs)
    assert (cells[3], sign[3]) == (0, 0)  # building 4 is not on the grid
