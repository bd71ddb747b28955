"""Buildings from a DSM (ground filter, objects, outlines) and their damage classes."""

import numpy as np
import pytest

from geocd.change.building_layer import check_building_layer
from geocd.change.dsm_buildings import DSMBuildingParams, buildings_from_dsm, classify_damage, ground_model
from geocd.consistency import ChangeResult
from geocd.geodesy import AOIGrid

GRID = AOIGrid.from_bounds(500000.0, 4000000.0, 500150.0, 4000150.0, 0.5, "EPSG:32637")


def _scene(rng):
    H, W = GRID.shape
    r, c = np.mgrid[0:H, 0:W]
    ground = 700.0 + 0.02 * c * 0.5 + 0.01 * r * 0.5  # sloping terrain (2 % and 1 %)
    z = ground + rng.normal(0, 0.15, (H, W))
    boxes = {
        1: (20, 60, 20, 80, 15.0),
        2: (20, 60, 84, 130, 24.0),  # two touching blocks of different height
        3: (120, 170, 30, 70, 12.0),
        4: (200, 260, 150, 200, 18.0),
        5: (150, 200, 220, 280, 9.0),
    }
    for _, (r0, r1, c0, c1, h) in boxes.items():
        z[r0:r1, c0:c1] = ground[r0:r1, c0:c1] + h + rng.normal(0, 0.1, (r1 - r0, c1 - c0))
    # a tree: rough blob
    tr = (r - 80) ** 2 + (c - 250) ** 2 < 12**2
    z[tr] = ground[tr] + 6 + rng.normal(0, 1.8, tr.sum())
    z[rng.random(z.shape) < 0.1] = np.nan  # stereo gaps
    return z, ground, boxes


def test_ground_and_objects():
    rng = np.random.default_rng(1)
    z, ground, boxes = _scene(rng)
    bld, dtm, labels = buildings_from_dsm(z, GRID)
    off = np.ones(z.shape, bool)
    for r0, r1, c0, c1, _ in boxes.values():
        off[max(r0 - 6, 0) : r1 + 6, max(c0 - 6, 0) : c1 + 6] = False
    assert np.median(np.abs(dtm - ground)[off]) < 0.3
    assert np.abs(dtm - ground).max() < 2.0  # under buildings too
    assert len(bld) == 5, bld  # touching blocks split, tree dropped
    areas = sorted(bld.geometry.area)
    want = sorted((r1 - r0) * (c1 - c0) * 0.25 for (r0, r1, c0, c1, _) in boxes.values())
    assert np.allclose(areas, want, rtol=0.15)
    assert (bld.rectangularity > 0.9).all()


def test_buildings_of_different_heights_wall_to_wall_are_two_objects():
    """A 15 m and a 24 m block sharing a wall (no neck for the distance watershed), a gabled house (its two
    facets one object) and a block with a 2 m parapet: the height step (``split_steps``, an option) splits the
    first pair only."""
    from geocd.change.dsm_buildings import building_objects

    rng = np.random.default_rng(5)
    H, W = GRID.shape
    r, c = np.mgrid[0:H, 0:W]
    ground = 700.0 + 0.01 * c * 0.5
    z = ground + rng.normal(0, 0.15, (H, W))
    z[40:80, 40:80] = ground[40:80, 40:80] + 15.0
    z[40:80, 80:120] = ground[40:80, 80:120] + 24.0  # wall to wall, 9 m higher
    house = (slice(150, 174), slice(40, 80))  # 12 m deep, 35° pitched roof over eaves at 6 m
    z[house] = ground[house] + 6.0 + np.tan(np.radians(35)) * (6.0 - np.abs((r[house] - 161.5) * 0.5))
    z[150:190, 150:200] = ground[150:190, 150:200] + 12.0
    z[150:152, 150:200] += 2.0  # a parapet
    z += rng.normal(0, 0.1, (H, W))
    dtm, gr = ground_model(z, 0.5)
    labels = building_objects(z, dtm, 0.5, DSMBuildingParams(split_steps=True), ground=gr)
    assert labels.max() == 4, labels.max()
    assert labels[60, 60] != labels[60, 100]
    assert labels[155, 60] == labels[170, 60]
    assert labels[151, 175] == labels[170, 175]
    off = building_objects(z, dtm, 0.5, ground=gr)  # the default: no split at height steps
    assert off.max() == 3 and off[60, 60] == off[60, 100]


def _result(z_a, z_b, changed_lower, changed_upper):
    dz = (z_b - z_a).astype(np.float32)
    conf = np.zeros(z_a.shape, np.float32)
    conf[changed_lower | changed_upper] = 99.0
    ch = np.sign(np.nan_to_num(dz)).astype(np.int8) * (conf > 0)
    obs = np.isfinite(dz)
    conf[~obs] = np.nan
    return ChangeResult(
        dz, dz / 2.0, np.zeros_like(dz), conf, ch.astype(np.int8), obs.astype(np.int16), GRID, (90.0, 95.0, 99.0)
    )


def test_damage_classes():
    rng = np.random.default_rng(2)
    z_a, ground, boxes = _scene(rng)
    z_b = z_a.copy()
    r0, r1, c0, c1, _ = boxes[1]
    z_b[r0:r1, c0:c1] = ground[r0:r1, c0:c1] + 1.0  # collapsed (rubble 1 m)
    r0, r1, c0, c1, _ = boxes[2]
    z_b[r0:r1, c0 : c0 + 15] = ground[r0:r1, c0 : c0 + 15] + 3.0  # part of the block gone
    r0, r1, c0, c1, _ = boxes[3]
    z_b[r0:r1, c0:c1] -= 3.0  # top storey gone everywhere
    z_b[60:100, 170:210] = ground[60:100, 170:210] + 10.0  # a new building on open ground
    low = np.nan_to_num(z_b - z_a) < -2
    up = np.nan_to_num(z_b - z_a) > 2
    res = _result(z_a, z_b, low, up)
    bld, dtm, _ = buildings_from_dsm(z_a, GRID)
    post, _, _ = buildings_from_dsm(z_b, GRID)
    import pandas as pd

    new = post[[g.intersection(bld.union_all()).area < 0.3 * g.area for g in post.geometry]]
    allb = pd.concat([bld, new], ignore_index=True)
    out = classify_damage(allb, res, GRID, z_a=z_a, z_b=z_b, dtm=dtm)
    check_building_layer(out)
    # without a ground model (tiled runs, demdiff) heights are taken above a ring around each building
    ring = classify_damage(allb, res, GRID, z_a=z_a, z_b=z_b)
    check_building_layer(ring)
    assert list(ring["class"]) == list(out["class"])
    assert np.abs(ring["height_before_m"] - out["height_before_m"]).max() < 1.0
    cls = {}
    for _, row in out.iterrows():
        c = row.geometry.centroid
        cls[(round((4000150 - c.y) / 0.5), round((c.x - 500000) / 0.5))] = row

    def at(r, c):
        return min(cls.items(), key=lambda kv: (kv[0][0] - r) ** 2 + (kv[0][1] - c) ** 2)[1]

    assert at(40, 50)["class"] == "collapsed"
    assert at(40, 107)["class"] == "partly collapsed"
    assert at(145, 50)["class"] == "lowered"
    assert at(80, 190)["class"] == "new"
    assert at(230, 175)["class"] == "unchanged" and at(230, 175)["confidence_pct"] == 0
    b1 = at(40, 50)
    assert b1["confidence_pct"] == 99.0
    assert b1["height_before_m"] == pytest.approx(15.0, abs=0.7) and b1["height_after_m"] == pytest.approx(1.0, abs=0.7)
    assert b1["volume_lost_m3"] == pytest.approx(14.0 * 40 * 60 * 0.25, rel=0.1)


def test_a_new_building_joined_to_a_standing_one_is_found():
    """A block built against a standing one of the same height: B's DSM has one object covering both (the
    watershed cannot split them), mostly over A's building, so judging whole objects of B (an object is new when
    < 30 % of it overlaps A's outlines) loses it; the parts of B's objects on A's ground find it."""
    from types import SimpleNamespace

    from geocd.change.dsm_buildings import new_objects
    from geocd.pipeline import _building_layer

    rng = np.random.default_rng(3)
    z_a, ground, boxes = _scene(rng)
    z_b = z_a.copy()
    r0, r1, c0, c1, h = boxes[4]
    z_b[r0:r1, c1 : c1 + 40] = ground[r0:r1, c1 : c1 + 40] + h + rng.normal(0, 0.1, (r1 - r0, 40))
    bld, dtm, lab_a = buildings_from_dsm(z_a, GRID)
    post, _, lab_b = buildings_from_dsm(z_b, GRID)
    merged = [g for g in post.geometry if g.area > 1.3 * (r1 - r0) * (c1 - c0) * 0.25]
    assert merged and merged[0].intersection(bld.union_all()).area > 0.3 * merged[0].area  # the old rule drops it
    new = new_objects(z_a, z_b, dtm, lab_b, GRID, labels_a=lab_a)
    assert len(new) == 1
    assert new.geometry.iloc[0].area == pytest.approx((r1 - r0) * 40 * 0.25, rel=0.15)
    up = np.nan_to_num(z_b - z_a) > 2
    res = _result(z_a, z_b, np.zeros_like(up), up)

    def rec(z):
        return SimpleNamespace(z_m=z, valid=np.isfinite(z))

    dmg, _ = _building_layer(None, res, GRID, [rec(z_a)], [rec(z_b)], None, 99.0, "A", "B")
    hit = dmg[dmg["class"] == "new"]
    assert len(hit) == 1 and hit["source"].iloc[0] == "B DSM (ground in A)"
    assert hit["height_after_m"].iloc[0] == pytest.approx(h, abs=1.0)
    assert (dmg[dmg["source"] == "A DSM"]["class"] == "unchanged").all()


def test_a_cleared_building_in_a_block_of_touching_ones_is_one_cleared_building():
    """Three buildings of one height wall to wall make one DSM object (no neck for the watershed to split).
    The middle one is cleared: it comes out as one collapsed building of its own size, and its two neighbours
    — apart now — as two unchanged buildings, not as one merged object a third changed."""
    from types import SimpleNamespace

    from geocd.pipeline import _building_layer

    rng = np.random.default_rng(4)
    H, W = GRID.shape
    r, c = np.mgrid[0:H, 0:W]
    ground = 700.0 + 0.02 * c * 0.5
    z_a = ground + rng.normal(0, 0.15, (H, W))
    r0, r1 = 100, 140  # 20 m deep
    cols = [(60, 92), (92, 124), (124, 156)]  # three 16 m wide buildings, wall to wall
    for c0, c1 in cols:
        z_a[r0:r1, c0:c1] = ground[r0:r1, c0:c1] + 15.0 + rng.normal(0, 0.1, (r1 - r0, c1 - c0))
    z_a[rng.random(z_a.shape) < 0.05] = np.nan
    bld, _, _ = buildings_from_dsm(z_a, GRID)
    assert len(bld) == 1  # the block is one object of the DSM
    z_b = z_a.copy()
    c0, c1 = cols[1]
    z_b[r0:r1, c0:c1] = ground[r0:r1, c0:c1] + 0.5 + rng.normal(0, 0.15, (r1 - r0, c1 - c0))  # cleared
    low = np.nan_to_num(z_b - z_a) < -2
    res = _result(z_a, z_b, low, np.zeros_like(low))

    def rec(z):
        return SimpleNamespace(z_m=z, valid=np.isfinite(z))

    dmg, _ = _building_layer(None, res, GRID, [rec(z_a)], [rec(z_b)], None, 99.0, "A", "B")
    check_building_layer(dmg)
    assert sorted(dmg["class"]) == ["collapsed", "unchanged", "unchanged"], dmg[["class", "area_m2"]]
    gone = dmg[dmg["class"] == "collapsed"].iloc[0]
    assert gone["area_m2"] == pytest.approx(16 * 20, rel=0.15)
    x = 500000.0 + 0.5 * (c0 + c1) / 2
    assert gone.geometry.bounds[0] < x < gone.geometry.bounds[2]
    assert np.allclose(dmg[dmg["class"] == "unchanged"]["area_m2"], 16 * 20, rtol=0.2)
    assert gone["height_before_m"] == pytest.approx(15.0, abs=0.7) and gone["height_after_m"] < 1.5


GRID_SMALL = AOIGrid.from_bounds(500000.0, 4000000.0, 500060.0, 4000060.0, 0.5, "EPSG:32637")


def _house_block_crown(seed, ground_sigma, roof_sigma, crown_sigma, crown_col_m, block: bool):
    """Flat ground (σ ``ground_sigma``), a gabled house (8 × 14 m, eaves 6 m, 35° roof, σ ``roof_sigma``), optionally
    a flat-roofed block (14 × 14 m, 9 m high, σ ``roof_sigma``), and a tree crown (a dome of radius 4.5 m on a 3 m
    trunk, leaves and gaps: σ ``crown_sigma`` per cell). Returns z and the masks (block None without one)."""
    rng = np.random.default_rng(seed)
    H, W = GRID_SMALL.shape
    r, c = np.mgrid[0:H, 0:W] * 0.5
    z = 500.0 + rng.normal(0, ground_sigma, (H, W))
    house = (r >= 10) & (r < 18) & (c >= 8) & (c < 22)
    z[house] = 506.0 + np.tan(np.radians(35)) * (4.0 - np.abs(r[house] - 14.0)) + rng.normal(0, roof_sigma, house.sum())
    blk = None
    if block:
        blk = (r >= 36) & (r < 50) & (c >= 6) & (c < 20)
        z[blk] = 509.0 + rng.normal(0, roof_sigma, blk.sum())
    d2 = (r - 40) ** 2 + (c - crown_col_m) ** 2
    crown = d2 < 4.5**2
    z[crown] = 503.0 + np.sqrt(4.5**2 - d2[crown]) + rng.normal(0, crown_sigma, crown.sum())
    return z, house, blk, crown


def _gabled_house_and_crown(seed):
    """Ground and roof σ 5 cm, a crown of σ 0.5 m: the scene the planarity rule was written on."""
    z, house, _, crown = _house_block_crown(seed, 0.05, 0.05, 0.5, 40, block=False)
    return z, house, crown


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planarity_rule_keeps_a_gabled_house_and_drops_a_tree(seed):
    """The planarity tree rule: a pitched roof is planar per facet (best of the nine 3 × 3 fits), a crown is
    not. The roughness rule drops the house too: its walls and ridge make it rough against smooth ground."""
    z, house, crown = _gabled_house_and_crown(seed)
    bld, _, lab = buildings_from_dsm(z, GRID_SMALL, DSMBuildingParams(tree_rule="planarity"))
    assert len(bld) == 1
    assert (lab[house] > 0).mean() > 0.9
    assert not (lab[crown] > 0).any()
    _, _, lab_old = buildings_from_dsm(z, GRID_SMALL, DSMBuildingParams(tree_rule="roughness"))
    assert not (lab_old[house] > 0).any()
    _, _, lab_off = buildings_from_dsm(z, GRID_SMALL, DSMBuildingParams(tree_rule="off"))
    assert (lab_off[crown] > 0).mean() > 0.5  # the crown is an object until a rule drops it


def test_unknown_tree_rule_is_a_config_error():
    from geocd.errors import ConfigError

    with pytest.raises(ConfigError, match="tree_rule"):
        DSMBuildingParams(tree_rule="ndvi")


def _town_like(seed):
    """Smooth ground (σ 2 cm, like the generated towns' DSMs), a gabled house and a flat-roofed block whose roofs
    are noisier than the ground (σ 6 cm), and a tree crown (σ 0.3 m)."""
    return _house_block_crown(seed, 0.02, 0.06, 0.3, 42, block=True)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_plane_rule_keeps_roofs_noisier_than_smooth_ground(seed):
    """The default tree rule: an object is a tree when its median best-of-nine plane residual exceeds 7.5 cm
    (or the ground's 75th percentile of it, if higher) — an absolute threshold, so roofs noisier than a very
    smooth ground stay. The former default (roughness > 2.5 × the ground's) drops both buildings here."""
    from geocd.change.dsm_buildings import best_plane_residual, tree_threshold_m

    z, house, block, crown = _town_like(seed)
    bld, dtm, lab = buildings_from_dsm(z, GRID_SMALL)
    assert DSMBuildingParams().tree_rule == "plane"
    assert len(bld) == 2
    assert (lab[house] > 0).mean() > 0.9 and (lab[block] > 0).mean() > 0.9
    assert not (lab[crown] > 0).any()
    best = best_plane_residual(z, 0.5)
    ground = (z - dtm) < 1.0
    assert tree_threshold_m(best, ground) == DSMBuildingParams().tree_residual_m  # smooth ground: the floor
    assert 0.01 < np.nanmedian(best[ground]) < 0.03
    _, _, lab_old = buildings_from_dsm(z, GRID_SMALL, DSMBuildingParams(tree_rule="roughness"))
    assert not (lab_old[house] > 0).any() and not (lab_old[block] > 0).any()


def test_plane_rule_threshold_follows_a_noisy_ground():
    """On a DSM noisier than the ones the 7.5 cm was measured on, the threshold rises to the ground's 75th
    percentile of the residual: roofs as planar as the ground stay (test_ground_and_objects' scene: ground
    σ 15 cm, roofs σ 10 cm), the rough blob goes."""
    from geocd.change.dsm_buildings import best_plane_residual, tree_threshold_m

    z, ground_true, boxes = _scene(np.random.default_rng(1))
    dtm, ground = ground_model(z, 0.5)
    best = best_plane_residual(z, 0.5)
    thr = tree_threshold_m(best, ground & (z - dtm < 3.0))
    assert thr > 1.3 * DSMBuildingParams().tree_residual_m
    assert thr == pytest.approx(np.percentile(best[ground & (z - dtm < 3.0) & np.isfinite(best)], 75))
    bld, _, _ = buildings_from_dsm(z, GRID)
    assert len(bld) == 5
    with pytest.raises(Exception, match="tree_residual_m"):
        DSMBuildingParams(tree_residual_m=0.0)


def test_tree_cells_are_the_objects_the_rule_drops():
    """tree_cells: the cells of the objects the tree rule drops (what a damage layer leaves out as vegetation) —
    the crown, not the house or the block; nothing with the rule off."""
    from geocd.change.dsm_buildings import tree_cells

    z, house, block, crown = _town_like(0)
    trees = tree_cells(z, 0.5)
    _, _, lab = buildings_from_dsm(z, GRID_SMALL)
    assert trees[crown].mean() > 0.8
    assert not trees[house].any() and not trees[block].any()
    assert not (trees & (lab > 0)).any()
    assert not tree_cells(z, 0.5, DSMBuildingParams(tree_rule="off")).any()


def test_a_lowered_part_makes_a_building_partly_collapsed():
    """The changed-part rule in the damage layer (an option): a 4 × 4 m lowered corner (under min_changed of
    the block) makes it partly collapsed at the level it was found, with the change map's mapping unit; off (the
    default), it stays unchanged; a part below the unit, or one the plane tree rule calls a tree, never counts."""
    import dataclasses

    rng = np.random.default_rng(3)
    z_a, ground, boxes = _scene(rng)
    z_b = z_a.copy()
    r0, r1, c0, c1, _ = boxes[3]  # 50 × 40 cells, 12 m
    z_b[r0 : r0 + 8, c0 : c0 + 8] -= 6.0  # 64 cells: 3.2 % of the block
    res = _result(z_a, z_b, np.nan_to_num(z_b - z_a) < -2, np.zeros(z_a.shape, bool))
    bld, dtm, _ = buildings_from_dsm(z_a, GRID)

    def block3(out):
        d = [
            (row.geometry.centroid.y - (4000150 - 145 * 0.5)) ** 2 + (row.geometry.centroid.x - 500025) ** 2
            for _, row in out.iterrows()
        ]
        return out.iloc[int(np.argmin(d))]

    on = DSMBuildingParams(changed_part=True)
    for mmu, params, want, conf in (
        (49, on, "partly collapsed", 99.0),
        (49, DSMBuildingParams(), "unchanged", 0.0),  # the default: off
        (65, on, "unchanged", 0.0),
    ):
        out = classify_damage(
            bld, dataclasses.replace(res, min_region_cells=mmu), GRID, z_a=z_a, z_b=z_b, dtm=dtm, params=params
        )
        b = block3(out)
        assert (b["class"], b["confidence_pct"]) == (want, conf), (mmu, params.changed_part, b["rule"])
        assert b["frac_lowered"] < 0.05
    # a crown standing on the corner before (rough to the plane tree rule) and felled: not building damage
    z_t = z_a.copy()
    z_t[r0 : r0 + 8, c0 : c0 + 8] += rng.normal(0, 1.0, (8, 8))
    res_t = _result(z_t, z_b, np.nan_to_num(z_b - z_t) < -2, np.zeros(z_a.shape, bool))
    out = classify_damage(
        bld, dataclasses.replace(res_t, min_region_cells=49), GRID, z_a=z_t, z_b=z_b, dtm=dtm, params=on
    )
    assert block3(out)["class"] == "unchanged"
