"""Scene generation and truth products (arrays)."""

from __future__ import annotations

import numpy as np
import pytest

from geocd.errors import ConfigError
from geocd.synth.scene import STOREY_M, TownParams, build_town, building_status
from geocd.synth.truth import (
    change_products,
    dsm,
    footprints_all,
    footprints_frame,
    image_change_mask,
    non3d_mask,
    truth_grid,
)


@pytest.fixture(scope="module")
def town():
    # a 300 m town with the default change list (generation only, no rendering: fast)
    return build_town(TownParams(seed=0))


def test_town_content_and_changes(town):
    from shapely.geometry import box

    aoi = box(*town.aoi)
    a, b = town.epochs["A"], town.epochs["B"]
    n_in = sum(bb.polygon().intersects(aoi) for bb in a.buildings)
    assert 25 <= n_in <= 40
    kinds = [c.kind for c in town.changes]
    assert kinds.count("new") >= 3 and kinds.count("demolished") >= 2
    assert kinds.count("raised") + kinds.count("lowered") >= 2
    assert any(k.startswith("car_") for k in kinds) and any(k.startswith("tree_") for k in kinds)
    assert {"repaint", "season"} <= set(kinds)
    assert {bb.roof for bb in a.buildings} == {"flat", "gabled"}
    assert len({bb.storeys for bb in a.buildings}) >= 3
    assert len(a.trees) > 50 and len(a.cars) > 10
    # raised/lowered by whole storeys, ids stable across epochs
    byid_a = {bb.building_id: bb for bb in a.buildings}
    byid_b = {bb.building_id: bb for bb in b.buildings}
    for c in town.changes:
        if c.kind in ("raised", "lowered"):
            d = byid_b[c.object_id].storeys - byid_a[c.object_id].storeys
            assert d * STOREY_M == pytest.approx(c.dz_m) and d != 0
            assert byid_a[c.object_id].polygon().equals(byid_b[c.object_id].polygon())
    # nothing stands inside anything else
    from shapely.geometry import Point

    for ep in (a, b):
        P = [bb.polygon() for bb in ep.buildings]
        assert not any(P[i].intersection(P[j]).area > 0.01 for i in range(len(P)) for j in range(i))
        assert not any(Point(t.cx, t.cy).buffer(t.crown_r).intersects(q) for t in ep.trees for q in P)
        assert not any(c.body.polygon().intersects(q) for c in ep.cars for q in P)
    st = building_status(town)
    assert set(st["A"].values()) <= {"demolished", "raised", "lowered", "unchanged"}
    assert set(st["B"].values()) <= {"new", "raised", "lowered", "unchanged"}
    # changes stay inside the AOI
    for c in town.changes:
        if c.kind in ("new", "demolished", "raised", "lowered"):
            bb = byid_a.get(c.object_id) or byid_b.get(c.object_id)
            assert aoi.contains(bb.polygon())


def test_same_seed_same_town_other_seed_other_town(town):
    again = build_town(TownParams(seed=0))
    assert again.epochs["A"].buildings == town.epochs["A"].buildings
    assert again.changes == town.changes
    np.testing.assert_array_equal(again.terrain.height_m, town.terrain.height_m)
    other = build_town(TownParams(seed=1))
    assert other.epochs["A"].buildings != town.epochs["A"].buildings


def test_parameters_are_validated():
    with pytest.raises(ConfigError):
        TownParams(size_m=5.0)
    with pytest.raises(ConfigError, match="unknown change"):
        TownParams(changes=("new", "earthquake"))
    t = build_town(TownParams(seed=3, size_m=120.0, changes=("new",), n_new=1))
    assert [c.kind for c in t.changes] == ["new"] or {c.kind for c in t.changes} <= {"new", "tree_removed"}


def test_truth_dsm_change_mask_and_footprints(tiny_town, tiny_scenes):
    grid = truth_grid(tiny_town, 0.5)
    assert grid.posting_m == 0.5 and grid.crs.to_epsg() == tiny_town.frame.epsg
    za, ca = dsm(tiny_town, tiny_scenes["A"], grid)
    zb, cb = dsm(tiny_town, tiny_scenes["B"], grid)
    mask, cls, sign = change_products(za, zb, ca, cb, 0.5, 1.0)
    assert mask.any() and set(np.unique(cls)) <= {0, 1, 2, 3}
    assert np.all((np.abs(zb - za) > 1.0) >= mask.astype(bool))  # only super-threshold cells
    # every changed building shows up in the mask with the right sign
    X, Y = grid.xy()
    x, y = X - tiny_town.frame.e0, Y - tiny_town.frame.n0
    from shapely import contains_xy

    for c in tiny_town.changes:
        if c.kind not in ("new", "demolished", "raised", "lowered"):
            continue
        ep = "A" if c.kind == "demolished" else "B"
        b = next(bb for bb in tiny_town.epochs[ep].buildings if bb.building_id == c.object_id)
        inside = contains_xy(b.polygon().buffer(-0.6), x, y)
        assert mask[inside].mean() > 0.95
        assert np.all(sign[inside & (mask > 0)] == (1 if c.dz_m > 0 else -1))
    fa = footprints_frame(tiny_town, "A")
    fb = footprints_frame(tiny_town, "B")
    fall = footprints_all(tiny_town)
    assert set(fa.columns) >= {"building_id", "status", "height_m", "geometry"}
    assert fa.crs.to_epsg() == tiny_town.frame.epsg
    assert len(fall) == len(set(fa.building_id) | set(fb.building_id))
    common = set(fa.building_id) & set(fb.building_id)
    sa, sb = fa.set_index("building_id")["status"], fb.set_index("building_id")["status"]
    assert all(sa[i] == sb[i] for i in common)
    n3 = non3d_mask(tiny_town, tiny_scenes["A"], tiny_scenes["B"], grid, mask)
    assert (n3 == 2).any() and not (n3.astype(bool) & mask.astype(bool)).any()


def test_image_change_mask_sees_new_building(tiny_params, tiny_town, tiny_scenes):
    from geocd.synth.generate import make_satellite_cameras

    cam = make_satellite_cameras(tiny_params, tiny_town)["A_sat1"]
    m, frac = image_change_mask(tiny_town, cam, tiny_scenes["A"], tiny_scenes["B"])
    assert m.shape == (cam.height, cam.width) and m.dtype == np.uint8
    new = next(c for c in tiny_town.changes if c.kind == "new")
    b = next(bb for bb in tiny_town.epochs["B"].buildings if bb.building_id == new.object_id)
    lon, lat = tiny_town.frame.to_lonlat(b.parts[0].cx, b.parts[0].cy)
    c, r = cam.project(lon, lat, b.eave_m)  # roof centre of the new building, seen in an epoch-A image
    assert m[int(r), int(c)] == 1
    assert 0.0 < m.mean() < 0.5
    # identical epochs: nothing changes
    m0, _ = image_change_mask(tiny_town, cam, tiny_scenes["A"], tiny_scenes["A"])
    assert not m0.any()


def test_a_town_without_cars_gives_empty_layers_with_their_columns():
    """A small town may hold no car or tree: its truth layers are empty, not an error."""
    from geocd.synth.truth import objects_frame

    from geocd.synth.generate import SynthParams

    t = build_town(SynthParams(seed=3, size_m=60.0).town_params())
    for what, cols in (("cars", {"car_id", "height_m"}), ("trees", {"tree_id", "crown_r_m", "top_m"})):
        for epoch in ("A", "B"):
            f = objects_frame(t, epoch, what)
            assert cols | {"geometry"} <= set(f.columns) and f.crs is not None
    assert len(objects_frame(t, "B", "cars")) == 0  # the case this guards (seed 3, 60 m: no car in epoch B)
