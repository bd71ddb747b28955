"""Each numba kernel of geocd.volume agrees with its pure-numpy reference."""

from __future__ import annotations

import numpy as np
import pytest

from geocd.geodesy import LocalFrame
from geocd.volume import VolumeGeometry, VolumeModel, VolumeParams, refine_model
from geocd.volume import _kernels as K
from geocd.volume.update import RayScratch

E = np.zeros(0)


def _random_model(seed=0, n_bins=2):
    geom = VolumeGeometry(
        LocalFrame(10.0, 45.0, 100.0), (-6.0, -4.0, -2.0), 4.0, (3, 2, 2), 3, "EPSG:32632", (0, 0, 1, 1)
    )
    m = VolumeModel.create(geom, VolumeParams(n_bins=n_bins), init_depth=1)
    rng = np.random.default_rng(seed)
    for _ in range(2):  # random refinement down to the finest level in places
        leaves = np.nonzero((m.child < 0) & (m.level < 3))[0]
        pick = rng.choice(leaves, size=max(1, leaves.size // 3), replace=False)
        m.alpha[:] = 1e-3
        m.alpha[pick] = 10.0
        refine_model(m, 0.3)
    m.alpha[:] = rng.uniform(0.0, 2.0, m.n_nodes).astype(np.float32)
    # random appearance in bin 0 (some cells empty), bin 1 empty
    for c in range(m.n_nodes):
        k = rng.integers(0, 4)
        for j in range(k):
            m.app[c, 0, j] = [rng.uniform(0, 1), rng.uniform(0.03, 0.2), rng.uniform(0.1, 1), rng.uniform(1, 5)]
    return m


def _random_rays(geom, n, seed=1):
    rng = np.random.default_rng(seed)
    lo, hi = geom.box_lo, geom.box_hi
    target = lo + rng.uniform(0, 1, (n, 3)) * (hi - lo)
    d = rng.normal(size=(n, 3))
    d[:, 2] = -np.abs(d[:, 2]) - 0.2
    d[: n // 8] = [0.0, 0.0, -1.0]  # axis-aligned rays along cell faces' normals
    d[n // 8 : n // 4, :2] = np.round(d[n // 8 : n // 4, :2])  # rays in axis planes
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = target - 30.0 * d
    o[n // 8 : n // 4 - 4] = np.round(o[n // 8 : n // 4 - 4] * 2) / 2  # some start on cell faces
    return o, d


def test_trace_matches_reference():
    m = _random_model()
    geo = m.geometry.geo_array()
    lo, hi = m.geometry.box_lo, m.geometry.box_hi
    o, d = _random_rays(m.geometry, 200)
    sc = RayScratch(geo)
    n_checked = 0
    for r in range(len(o)):
        t0, t1 = K.clip_ray(*o[r], *d[r], lo, hi)
        cells, lens, starts = K.trace_ray_ref(o[r], d[r], geo, m.block_root, m.child, lo, hi)
        if t1 <= t0:
            assert cells.size == 0
            continue
        n = K.trace_ray(*o[r], *d[r], t0, t1, geo, m.block_root, m.child, sc.seg_cell, sc.seg_len, sc.seg_t)
        got_c, got_l = sc.seg_cell[:n], sc.seg_len[:n]
        # the kernel may emit sub-micrometre slivers at edges: merge them away before comparing
        keep = got_l > 1e-5
        gc, gl = got_c[keep], got_l[keep]
        merged_c, merged_l = [], []
        for c, ln in zip(gc, gl):
            if merged_c and merged_c[-1] == c:
                merged_l[-1] += ln
            else:
                merged_c.append(c)
                merged_l.append(ln)
        rk = lens > 1e-5
        np.testing.assert_array_equal(np.array(merged_c), cells[rk])
        np.testing.assert_allclose(np.array(merged_l), lens[rk], atol=3e-5)
        assert abs(sc.seg_len[:n].sum() - (t1 - t0)) < 1e-6
        assert np.all(m.child[sc.seg_cell[:n]] < 0)
        n_checked += 1
    assert n_checked > 100


def test_trace_buffer_never_overflows():
    m = _random_model()
    geo = m.geometry.geo_array()
    sc = RayScratch(geo)
    lo, hi = m.geometry.box_lo, m.geometry.box_hi
    # a diagonal ray through the whole box at the finest level everywhere
    fg = VolumeModel.create(m.geometry, init_depth=3)
    o = lo - 1.0
    d = (hi - lo) / np.linalg.norm(hi - lo)
    t0, t1 = K.clip_ray(*o, *d, lo, hi)
    n = K.trace_ray(*o, *d, t0, t1, geo, fg.block_root, fg.child, sc.seg_cell, sc.seg_len, sc.seg_t)
    assert n < sc.seg_cell.size
    assert abs(sc.seg_len[:n].sum() - (t1 - t0)) < 1e-9


@pytest.mark.parametrize("b,cell_mean", [(0, False), (1, False), (-1, False), (0, True)])
def test_update_rays_matches_reference(b, cell_mean):
    m = _random_model()
    geo = m.geometry.geo_array()
    lo, hi = m.geometry.box_lo, m.geometry.box_hi
    o, d = _random_rays(m.geometry, 120, seed=3)
    obs = np.random.default_rng(4).uniform(0, 1, len(o))
    obs[::17] = np.nan
    n = m.n_nodes
    cell_obs = np.random.default_rng(11).uniform(0, 1, n) if cell_mean else np.zeros(0)
    cell_pa = np.zeros(n) if cell_mean else np.zeros(0)
    if cell_mean:
        K.mog_density_cells(m.app, b, cell_obs, 0.7, cell_pa)
    acc = np.zeros((4, n))
    sc = RayScratch(geo)
    K.update_rays(
        o,
        d,
        obs,
        cell_pa,
        lo,
        hi,
        geo,
        m.block_root,
        m.child,
        m.alpha,
        m.app,
        b,
        1.0,
        0.7,
        acc[0],
        acc[1],
        acc[2],
        acc[3],
        sc.seg_cell,
        sc.seg_len,
        sc.seg_t,
        sc.a,
        sc.b,
        sc.c,
        sc.d,
    )
    ref = K.update_rays_ref(o, d, obs, cell_obs, lo, hi, geo, m.block_root, m.child, m.alpha, m.app, b, 1.0, 0.7, n)
    np.testing.assert_allclose(acc, ref, rtol=1e-6, atol=1e-6)


def test_seglen_rays_matches_reference():
    m = _random_model()
    geo = m.geometry.geo_array()
    lo, hi = m.geometry.box_lo, m.geometry.box_hi
    o, d = _random_rays(m.geometry, 120, seed=12)
    obs = np.random.default_rng(13).uniform(0, 1, len(o))
    obs[::7] = np.nan
    acc = np.zeros((2, m.n_nodes))
    sc = RayScratch(geo)
    K.seglen_rays(o, d, obs, lo, hi, geo, m.block_root, m.child, acc[0], acc[1], sc.seg_cell, sc.seg_len, sc.seg_t)
    ref = K.update_rays_ref(
        o, d, obs, np.zeros(0), lo, hi, geo, m.block_root, m.child, m.alpha, m.app, -1, 1.0, 0.7, m.n_nodes
    )
    np.testing.assert_allclose(acc, ref[[0, 2]], rtol=1e-9, atol=1e-9)


def test_render_rays_matches_reference():
    m = _random_model()
    geo = m.geometry.geo_array()
    lo, hi = m.geometry.box_lo, m.geometry.box_hi
    o, d = _random_rays(m.geometry, 120, seed=5)
    obs = np.random.default_rng(6).uniform(0, 1, len(o))
    obs[::5] = np.nan
    out = np.zeros((4, len(o)))
    sc = RayScratch(geo)
    K.render_rays(
        o,
        d,
        obs,
        lo,
        hi,
        geo,
        m.block_root,
        m.child,
        m.alpha,
        m.app,
        0,
        1.0,
        0.5,
        0.7,
        E,
        E,
        E,
        out[0],
        out[1],
        out[2],
        out[3],
        sc.seg_cell,
        sc.seg_len,
        sc.seg_t,
    )
    ref = K.render_rays_ref(o, d, obs, lo, hi, geo, m.block_root, m.child, m.alpha, m.app, 0, 1.0, 0.5, 0.7)
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-6, equal_nan=True)


def test_density_nxn_matches_brute_force():
    m = _random_model()
    geo = m.geometry.geo_array()
    lo, hi = m.geometry.box_lo, m.geometry.box_hi
    rows, cols = 5, 6
    o, d = _random_rays(m.geometry, rows * cols, seed=7)
    img = np.random.default_rng(8).uniform(0, 1, (rows, cols))
    img[1, 2] = np.nan
    out = np.zeros((rows, cols))
    sc = RayScratch(geo)
    K.density_nxn(
        o,
        d,
        img,
        cols,
        1,
        lo,
        hi,
        geo,
        m.block_root,
        m.child,
        m.alpha,
        m.app,
        0,
        1.0,
        0.7,
        E,
        E,
        E,
        out,
        sc.seg_cell,
        sc.seg_len,
        sc.seg_t,
        sc.a,
    )
    ref = np.zeros((rows, cols))
    for i in range(rows):
        for j in range(cols):
            if not np.isfinite(img[i, j]):
                continue
            best = 0.0
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    a, bb = i + di, j + dj
                    if 0 <= a < rows and 0 <= bb < cols:
                        r = a * cols + bb
                        v = K.render_rays_ref(
                            o[r : r + 1],
                            d[r : r + 1],
                            np.array([img[i, j]]),
                            lo,
                            hi,
                            geo,
                            m.block_root,
                            m.child,
                            m.alpha,
                            m.app,
                            0,
                            1.0,
                            0.5,
                            0.7,
                        )[0, 0]
                        best = max(best, v)
            ref[i, j] = best
    np.testing.assert_allclose(out, ref, rtol=1e-7, atol=1e-12)


def test_mog_update_matches_reference():
    rng = np.random.default_rng(9)
    app = np.zeros((1, 1, 3, 4), dtype=np.float32)
    app[..., 1] = 0.1
    ref = app[0, 0].astype(float)
    for _ in range(300):
        x = float(rng.choice([rng.normal(0.3, 0.02), rng.normal(0.7, 0.05), rng.uniform()]))
        w = float(rng.uniform(0.01, 1.0))
        K.mog_update(app, 0, 0, x, w, 0.1, 0.03, 2.5)
        ref = K.mog_update_ref(ref, x, w, 0.1, 0.03, 2.5)
        np.testing.assert_allclose(app[0, 0], ref, rtol=2e-4, atol=2e-5)
        ref = app[0, 0].astype(float)  # follow float32 rounding of the kernel
    assert abs(app[0, 0, :, 2].sum() - 1.0) < 1e-4
    # the dominant modes are the two clusters
    mus = sorted(app[0, 0, :2, 0].tolist())
    assert abs(mus[0] - 0.3) < 0.05 and abs(mus[1] - 0.7) < 0.05


def test_mog_density_and_mean_match_reference():
    m = _random_model()
    rng = np.random.default_rng(10)
    for c in rng.integers(0, m.n_nodes, 50):
        x = rng.uniform()
        for b in (0, 1, -1):
            assert abs(K.mog_density(m.app, c, b, x, 0.7) - K.mog_density_ref(m.app, c, b, x, 0.7)) < 1e-6
            assert abs(K.mog_mean(m.app, c, b, 0.7) - K.mog_mean_ref(m.app, c, b, 0.7)) < 1e-6


@pytest.mark.parametrize("b", [0, 1, -1])
def test_mog_density_cells_matches_reference_and_per_cell_density(b):
    m = _random_model()
    x = np.random.default_rng(14).uniform(0, 1, m.n_nodes)
    x[::9] = np.nan  # cells no ray crossed have no mean observation
    out = np.zeros(m.n_nodes)
    K.mog_density_cells(m.app, b, x, 0.7, out)
    np.testing.assert_allclose(out, K.mog_density_cells_ref(m.app, b, x, 0.7), rtol=1e-6, atol=1e-6)
    # the very same figure as the per-cell kernel update_rays used to call for each segment
    per_cell = np.array([K.mog_density(m.app, c, b, x[c], 0.7) for c in range(m.n_nodes)])
    assert np.array_equal(out, per_cell, equal_nan=True)


def test_node_boxes_contain_their_rays_points():
    m = _random_model()
    from geocd.volume.relight import node_boxes

    c, s = node_boxes(m)
    geo = m.geometry.geo_array()
    rng = np.random.default_rng(14)
    leaves = np.nonzero(m.child < 0)[0]
    for node in rng.choice(leaves, 60, replace=False):
        p = c[node] + rng.uniform(-0.49, 0.49, 3) * s[node]
        assert K._leaf_at_ref(p, geo, m.block_root, m.child) == node
    np.testing.assert_allclose(s[leaves], 4.0 / 2.0 ** m.level[leaves])


def test_sun_visibility_matches_reference():
    m = _random_model()
    from geocd.volume.relight import node_boxes, sun_vector_enu

    c, s = node_boxes(m)
    geo = m.geometry.geo_array()
    lo, hi = m.geometry.box_lo, m.geometry.box_hi
    cells = np.nonzero(m.child < 0)[0][::3].astype(np.int64)
    sun = sun_vector_enu((140.0, 50.0))
    out = np.empty(cells.size)
    sc = RayScratch(geo)
    K.sun_visibility(
        cells, c, s, sun, 1.0, lo, hi, geo, m.block_root, m.child, m.alpha, out, sc.seg_cell, sc.seg_len, sc.seg_t
    )
    ref = K.sun_visibility_ref(cells, c, s, sun, 1.0, lo, hi, geo, m.block_root, m.child, m.alpha)
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-9)


def test_ray_cell_average_matches_reference():
    m = _random_model()
    geo = m.geometry.geo_array()
    lo, hi = m.geometry.box_lo, m.geometry.box_hi
    o, d = _random_rays(m.geometry, 80, seed=15)
    vals = np.random.default_rng(16).uniform(0, 1, (m.n_nodes, 2))
    out = np.empty((len(o), 2))
    ws = np.empty(len(o))
    sc = RayScratch(geo)
    K.ray_cell_average(
        o, d, lo, hi, geo, m.block_root, m.child, m.alpha, vals, out, ws, sc.seg_cell, sc.seg_len, sc.seg_t
    )
    for r in range(len(o)):
        cells, lens, _ = K.trace_ray_ref(o[r], d[r], geo, m.block_root, m.child, lo, hi)
        pq = 1 - np.exp(-m.alpha[cells].astype(float) * lens)
        vis = np.concatenate([[1.0], np.cumprod(1 - pq)])
        w = vis[:-1] * pq
        assert abs(ws[r] - w.sum()) < 1e-9
        if w.sum() > 0:
            np.testing.assert_allclose(out[r], (w[:, None] * vals[cells]).sum(0) / w.sum(), rtol=1e-9)


def test_compaction_and_coarsening_keep_rays_consistent():
    from geocd.volume.refine import coarsen_model, compact_model

    m = _random_model()
    geo = m.geometry.geo_array()
    lo, hi = m.geometry.box_lo, m.geometry.box_hi
    o, d = _random_rays(m.geometry, 60, seed=17)
    obs = np.random.default_rng(18).uniform(0, 1, len(o))

    def render(mm):
        out = np.zeros((4, len(o)))
        sc = RayScratch(geo)
        K.render_rays(
            o,
            d,
            obs,
            lo,
            hi,
            geo,
            mm.block_root,
            mm.child,
            mm.alpha,
            mm.app,
            0,
            1.0,
            0.5,
            0.7,
            E,
            E,
            E,
            out[0],
            out[1],
            out[2],
            out[3],
            sc.seg_cell,
            sc.seg_len,
            sc.seg_t,
        )
        return out

    before = render(m)
    m2 = m.copy()
    compact_model(m2)
    np.testing.assert_allclose(render(m2), before, rtol=1e-12, equal_nan=True)
    # free space everywhere: every split is undone, α is preserved as a density
    m3 = m.copy()
    m3.alpha[:] = 1e-3
    coarsen_model(m3, 0.3)
    assert m3.n_nodes == int(np.prod(m3.geometry.n_blocks))
    assert np.all(m3.child < 0)
    np.testing.assert_allclose(m3.alpha, 1e-3, rtol=1e-6)
    # dense cells stay refined
    m4 = m.copy()
    m4.alpha[:] = 50.0
    n4 = m4.n_nodes
    coarsen_model(m4, 0.3)
    assert m4.n_nodes == n4


def test_mapped_density_matches_reference_and_identity():
    m = _random_model()
    rng = np.random.default_rng(19)
    for c in rng.integers(0, m.n_nodes, 40):
        x = rng.uniform()
        assert abs(K.mog_density_mapped(m.app, c, 0, x, 0.7, 0.0, 1.0, 0.0) - K.mog_density(m.app, c, 0, x, 0.7)) < 1e-9
        a, b, s = 0.1, 0.8, 0.05
        mm = m.app.copy()
        mm[c, 0, :, 0] = a + b * mm[c, 0, :, 0]
        mm[c, 0, :, 1] = np.sqrt((b * mm[c, 0, :, 1]) ** 2 + s * s)
        assert abs(K.mog_density_mapped(m.app, c, 0, x, 0.7, a, b, s) - K.mog_density_ref(mm, c, 0, x, 0.7)) < 1e-5


def test_surface_sun_matches_reference():
    m = _random_model()
    geo = m.geometry.geo_array()
    lo, hi = m.geometry.box_lo, m.geometry.box_hi
    o, d = _random_rays(m.geometry, 50, seed=20)
    out = np.zeros((4, len(o)))
    sc = RayScratch(geo)
    K.render_rays(
        o,
        d,
        np.full(len(o), np.nan),
        lo,
        hi,
        geo,
        m.block_root,
        m.child,
        m.alpha,
        m.app,
        0,
        1.0,
        0.5,
        0.7,
        E,
        E,
        E,
        out[0],
        out[1],
        out[2],
        out[3],
        sc.seg_cell,
        sc.seg_len,
        sc.seg_t,
    )
    from geocd.volume.relight import sun_vector_enu

    sun = sun_vector_enu((150.0, 45.0))
    s = np.empty(len(o))
    K.surface_sun(
        o, d, out[3], sun, 0.25, 0.5, lo, hi, geo, m.block_root, m.child, m.alpha, s, sc.seg_cell, sc.seg_len, sc.seg_t
    )
    for r in range(len(o)):
        if not np.isfinite(out[3, r]):
            assert s[r] == 1.0
            continue
        p = o[r] + out[3, r] * d[r] + np.array([0, 0, 0.25])
        cells, lens, tt = K.trace_ray_ref(p, sun, geo, m.block_root, m.child, lo, hi)
        part = np.clip(tt + lens - np.maximum(tt, 0.5), 0, None)
        assert abs(s[r] - np.exp(-np.sum(m.alpha[cells] * part))) < 1e-6
