"""Renderer kernels against their pure-numpy references."""

from __future__ import annotations

import numpy as np
import pytest

from geocd.synth import _kernels as K
from geocd.synth.render import scene_z_band


def test_value_noise_matches_reference():
    rng = np.random.default_rng(0)
    x, y, z = (rng.uniform(-500, 500, 20000) for _ in range(3))
    out = np.empty(x.size)
    K.vnoise_many(x, y, z, 7, out)
    ref = K.vnoise_ref(x, y, z, 7)
    assert np.abs(out - ref).max() < 1e-12
    assert 0.0 <= out.min() and out.max() < 1.0
    # continuous across lattice cells, different for other seeds
    a = np.empty(2)
    K.vnoise_many(np.array([2.0 - 1e-9, 2.0 + 1e-9]), np.array([0.3, 0.3]), np.array([0.1, 0.1]), 7, a)
    assert abs(a[0] - a[1]) < 1e-6
    b = np.empty(x.size)
    K.vnoise_many(x, y, z, 8, b)
    assert np.mean(np.abs(b - out)) > 0.1


def _random_rays(town, n, rng, steep=True):
    """Rays from above the scene towards random ground points, with random obliquity."""
    x0, y0, x1, y1 = town.aoi
    tx, ty = rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)
    zt = town.terrain.at(tx, ty) + rng.uniform(-1, 8, n)
    el = np.radians(rng.uniform(55, 89.9, n) if steep else rng.uniform(20, 89.9, n))
    az = rng.uniform(0, 2 * np.pi, n)
    d = -np.column_stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
    top = 240.0
    s = (top - zt) / -d[:, 2]
    o = np.column_stack([tx, ty, zt]) - s[:, None] * d
    return np.ascontiguousarray(o), np.ascontiguousarray(d), np.full(n, 200.0)


@pytest.mark.parametrize("steep", [True, False])
def test_first_hit_matches_brute_force(tiny_town, tiny_scenes, steep):
    S = tiny_scenes["A"]
    rng = np.random.default_rng(5)
    o, d, tm = _random_rays(tiny_town, 1500, rng, steep)
    t = np.empty(len(tm))
    ob = np.empty(len(tm), np.int64)
    fc = np.empty(len(tm), np.int64)
    K.trace_first_hit(o, d, tm, S, t, ob, fc)
    tr, obr = K.first_hit_ref(S, o, d, tm)
    same = ob == obr
    # the reference samples the terrain every 1 cm: objects agree exactly, terrain to ~1e-4 m
    assert same.mean() > 0.995
    assert np.abs(t[same] - tr[same]).max() < 2e-3
    obj = same & (ob >= 0)
    assert obj.sum() > 50 and np.abs(t[obj] - tr[obj]).max() < 1e-9
    assert (ob >= 0).any() and (ob == -1).any()


def test_terrain_hit_lands_on_the_surface(tiny_town, tiny_scenes):
    S = tiny_scenes["A"]
    rng = np.random.default_rng(2)
    o, d, tm = _random_rays(tiny_town, 500, rng, steep=False)
    for i in range(500):
        t = K.terrain_hit(S.terr, S.terr_meta, S.terr_block_max, *o[i], *d[i], 0.0, tm[i])
        p = o[i] + t * d[i]
        assert abs(p[2] - tiny_town.terrain.at(p[0], p[1])) < 1e-6


def test_terrain_block_max_bounds_the_surface_and_skipping_keeps_every_hit(tiny_town, tiny_scenes):
    """The block maxima lie above the bilinear terrain everywhere (posts on the far edges included), and the march
    that passes the steps surely above them finds the very t of the march that evaluates every step."""
    S = tiny_scenes["A"]
    rng = np.random.default_rng(5)
    x0, y0, step = S.terr_meta[:3]
    ny, nx = S.terr.shape
    xs = rng.uniform(x0 - 5, x0 + step * (nx - 1) + 5, 5000)  # beyond the edges too (clamped)
    ys = rng.uniform(y0 - 5, y0 + step * (ny - 1) + 5, 5000)
    for x, y in zip(xs, ys):
        h, _, _ = K.terrain_at(S.terr, S.terr_meta, x, y)
        assert not K._above_block(S.terr, S.terr_meta, S.terr_block_max, x, y, h)
    flat_top = np.full((1, 1), np.inf)  # no step is ever surely above: every step evaluated
    o, d, tm = _random_rays(tiny_town, 300, rng, steep=False)
    for i in range(300):
        assert K.terrain_hit(S.terr, S.terr_meta, S.terr_block_max, *o[i], *d[i], 0.0, tm[i]) == K.terrain_hit(
            S.terr, S.terr_meta, np.broadcast_to(flat_top, S.terr_block_max.shape).copy(), *o[i], *d[i], 0.0, tm[i]
        )


def test_vertical_rays_give_object_tops(tiny_town, tiny_scenes):
    from geocd.synth.render import surface_height

    ep = tiny_town.epochs["A"]
    for b in ep.buildings:
        if b.roof == "flat":
            p = b.parts[0]
            z = surface_height(tiny_scenes["A"], np.array([p.cx]), np.array([p.cy]))
            assert z[0] == pytest.approx(b.eave_m, abs=1e-9)
        else:
            p = b.parts[0]
            z = surface_height(tiny_scenes["A"], np.array([p.cx]), np.array([p.cy]))  # on the ridge line
            assert z[0] == pytest.approx(b.top_m, abs=1e-9)
    for t in ep.trees:
        z = surface_height(tiny_scenes["A"], np.array([t.cx]), np.array([t.cy]))
        assert z[0] == pytest.approx(t.top_m, abs=1e-9)
    lo, hi = scene_z_band(tiny_scenes["A"])
    assert lo < tiny_town.terrain.height_m.min() and hi > max(b.top_m for b in ep.buildings)


def test_enu_rays_to_map_matches_exact_conversion(tiny_town):
    fr = tiny_town.frame
    rng = np.random.default_rng(4)
    n = 300
    o = np.column_stack([rng.uniform(-2e5, 2e5, n), rng.uniform(-2e5, 2e5, n), np.full(n, 6.2e5)])
    tgt = np.column_stack([rng.uniform(-100, 100, n), rng.uniform(-100, 100, n), rng.uniform(-10, 30, n)])
    d = tgt - o
    d /= np.linalg.norm(d, axis=1)[:, None]
    coef, scale, h0 = fr._poly
    A = np.empty((n, 3))
    D = np.empty((n, 3))
    L = np.empty(n)
    K.enu_rays_to_map(o, d, 40.0, -20.0, np.ascontiguousarray(coef), float(scale[0]), h0, A, D, L)
    s = (40.0 - o[:, 2]) / d[:, 2]
    p = o + s[:, None] * d
    ex = np.column_stack(fr.enu_to_map_exact(p[:, 0], p[:, 1], p[:, 2]))
    assert np.abs(A - ex).max() < 1e-6
    # the map-space chord passes within micrometres of the exact image of the target point
    ext = np.column_stack(fr.enu_to_map_exact(tgt[:, 0], tgt[:, 1], tgt[:, 2]))
    tt = np.sum((ext - A) * D, axis=1)
    assert np.linalg.norm(A + tt[:, None] * D - ext, axis=1).max() < 1e-4


def test_shadow_is_cast_behind_a_building(tiny_town, tiny_scenes):
    from shapely.geometry import LineString

    S = tiny_scenes["A"]
    b = max(tiny_town.epochs["A"].buildings, key=lambda b: b.top_m)
    sun = np.array([0.0, -np.cos(np.radians(40)), np.sin(np.radians(40))])  # from the south, 40° high
    poly = b.polygon()
    x = poly.centroid.x
    cut = LineString([(x, -1e4), (x, 1e4)]).intersection(poly)
    y_s, y_n = cut.bounds[1], cut.bounds[3]
    checked = 0
    # just north of the wall: in the building's shadow; just south: sunlit (when no other object is there)
    for y, expect in ((y_n + 0.5, True), (y_s - 0.5, False)):
        z = float(tiny_town.terrain.at(x, y))
        nx, ny, nz = K.surface_normal(S, -1, -1, x, y, z)
        shadow = K.in_shadow(S, x, y, z, nx, ny, nz, *sun)
        seen = K.first_hit(S, x, y, z + 50.0, 0.0, 0.0, -1.0, 0.0, 100.0)[1] == -1
        towards_sun = K.objects_hit(S, x, y, z + 0.01, *sun, 0.0, np.inf)[1]
        if seen and (expect or towards_sun < 0):
            assert shadow == expect
            checked += 1
    assert checked >= 1


def test_shading_matches_plain_reference(tiny_town, tiny_scenes):
    """render_rays (textures, normals, bump, shadow rays, sky) against the plain-Python re-implementation."""
    from geocd.synth.render import sun_direction_map
    from geocd.synth.sensors import sun_direction_enu

    S = tiny_scenes["B"]  # epoch B also has soil patches
    rng = np.random.default_rng(11)
    o, d, tm = _random_rays(tiny_town, 150, rng, steep=False)
    sun = sun_direction_map(tiny_town, sun_direction_enu(150.0, 35.0))
    light = np.array([1.0, 0.25])
    out = np.empty((150, 4))
    t = np.empty(150)
    ob = np.empty(150, np.int64)
    K.render_rays(o, d, tm, sun, light, S, out, t, ob)
    ref = K.shade_ref(S, o, d, tm, sun, light)
    close = np.all(np.abs(out - ref) <= 1e-3 * np.maximum(np.abs(ref), 0.05), axis=1)
    # rare disagreements: rays through an exact edge, or a shadow boundary within the reference's 1e-5 m terrain error
    assert close.mean() > 0.97
    on_objects = close & (ob >= 0)
    assert on_objects.sum() > 20
    assert np.abs(out[on_objects] - ref[on_objects]).max() < 1e-9
    assert (out[:, 0] < 0.5 * out[:, 0].max()).any() and (ref > 0).any()


def test_ground_material_matches_reference(tiny_town, tiny_scenes):
    S = tiny_scenes["B"]
    rng = np.random.default_rng(8)
    x0, y0, x1, y1 = tiny_town.extent
    x, y = rng.uniform(x0, x1, 3000), rng.uniform(y0, y1, 3000)
    out = np.empty(3000, np.int64)
    K.ground_material_many(S, x, y, out)
    ref = np.array([K.ground_material_ref(S, a, b) for a, b in zip(x, y)])
    np.testing.assert_array_equal(out, ref)
    assert len(np.unique(out)) >= 3  # grass, asphalt, pavement (and soil/markings)
