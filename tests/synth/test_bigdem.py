"""The large DEM pair generator: kernel == numpy reference, tiling-independent, exact truth."""

from __future__ import annotations

import json

import numpy as np
import rasterio

from geocd.synth.bigdem import DEMPairParams, dem_window, dem_window_ref, make_dem_pair, make_objects

P = DEMPairParams(size=400, posting_m=1.0, changes_per_km2=60, voids_per_km2=12, seed=3)


def test_kernel_matches_reference():
    obj = make_objects(P)
    assert (obj[:, 0] == 2).any() and (obj[:, 0] == 0).any() and (obj[:, 0] == 1).any()
    for which in ("a", "b", "truth"):
        k = dem_window(P, which, (37, 11, 300, 260), obj)
        r = dem_window_ref(P, which, (37, 11, 300, 260), obj)
        np.testing.assert_allclose(k, r, rtol=0, atol=1e-3)
        np.testing.assert_array_equal(np.isnan(k), np.isnan(r))


def test_windows_do_not_depend_on_tiling():
    obj = make_objects(P)
    whole = dem_window(P, "b", (0, 0, 400, 400), obj)
    part = dem_window(P, "b", (130, 250, 70, 90), obj)
    np.testing.assert_array_equal(part, whole[130:200, 250:340])


def test_make_dem_pair_small(tmp_path):
    paths = make_dem_pair(tmp_path, P, tile_size=128, scheduler="sync")
    truth = json.loads(paths["truth"].read_text())
    with rasterio.open(paths["dem_a"]) as a, rasterio.open(paths["dem_b"]) as b, rasterio.open(paths["truth_dh"]) as t:
        A, B, T = a.read(1), b.read(1), t.read(1)
        assert a.crs.to_epsg() == 32631 and a.res == (1.0, 1.0)
    obj = make_objects(P)
    np.testing.assert_array_equal(B, dem_window(P, "b", (0, 0, 400, 400), obj))
    np.testing.assert_array_equal(A, dem_window(P, "a", (0, 0, 400, 400), obj))
    # the truth's volumes are the sums of the truth raster
    fin = np.isfinite(T)
    assert truth["changed_cells"] == int(((T != 0) & fin).sum())
    np.testing.assert_allclose(truth["volume_raised_m3"], T[fin & (T > 0)].sum(dtype=np.float64), rtol=1e-6)
    assert np.isnan(B).sum() == (~fin).sum() > 0
    # slopes in every direction, a few tens of degrees at most
    gy, gx = np.gradient(A.astype(np.float64))
    s = np.degrees(np.arctan(np.hypot(gx, gy)))
    assert 3 < np.median(s) < 25 and s.max() < 60
    assert not (tmp_path / ".geocd-work").exists()
