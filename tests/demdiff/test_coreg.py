import numpy as np
import pytest

from geocd.demdiff import CoregParams, apply_shift, nuth_kaab, nmad
from geocd.errors import ConfigError, ProcessingError

from .synthetic import grid, pair

POST = (10.0, 10.0)


@pytest.mark.parametrize("shift", [(4.0, -6.0, 2.5), (-13.0, 7.5, -1.0), (0.0, 0.0, 0.0)])
def test_known_shift_is_recovered(shift):
    a, b, _ = pair(shift, noise_m=0.3)
    st = np.ones(a.grid.shape, bool)
    out, res = nuth_kaab(a.height_m, b.height_m, st, POST)
    # B(x) = A(x − d) + dz  →  the translation that aligns B is (−d, −dz)
    exp = (-shift[0], -shift[1], -shift[2])
    assert res.status == "ok" and res.applied == "horizontal+vertical" and res.converged
    np.testing.assert_allclose(res.shift_m[:2], exp[:2], atol=0.1 * POST[0])  # < 0.1 px
    assert abs(res.shift_m[2] - exp[2]) < 0.15
    assert all(np.isfinite(res.shift_sigma_m)) and max(res.shift_sigma_m[:2]) < 0.3 * POST[0]
    # residual dh after alignment is noise-level (bilinear resampling adds a little)
    d = out - a.height_m
    assert nmad(d[np.isfinite(d)]) < 1.0
    assert res.nmad_after_m < res.nmad_before_m or shift == (0.0, 0.0, 0.0)


def test_shift_is_within_its_sigma_statistically():
    errs = []
    for seed in range(6):
        a, b, _ = pair((6.0, 3.0, 0.0), noise_m=1.0, seed=seed)
        _, res = nuth_kaab(a.height_m, b.height_m, np.ones(a.grid.shape, bool), POST)
        errs.append((res.shift_m[0] + 6.0) / res.shift_sigma_m[0])
    # the jackknife σ is not wildly optimistic: |error| < 3σ in every run
    assert np.all(np.abs(errs) < 3.0), errs


def test_apply_shift_convention():
    a, b, _ = pair((5.0, -5.0, 1.0), noise_m=0.0)
    aligned = apply_shift(b.height_m, (-5.0, 5.0, -1.0), POST)
    d = aligned - a.height_m
    assert np.nanmax(np.abs(d[5:-5, 5:-5])) < 0.5


def test_tilt_term_removed():
    g = grid()
    a, b, _ = pair((0.0, 0.0, 0.0), noise_m=0.1)
    rr, cc = np.mgrid[0 : g.height, 0 : g.width]
    hb = b.height_m + (0.002 * (cc - g.width / 2) * 10 - 0.001 * (rr - g.height / 2) * 10).astype(np.float32)
    out, res = nuth_kaab(a.height_m, hb, np.ones(g.shape, bool), POST, CoregParams(tilt=True))
    assert res.tilt is not None
    np.testing.assert_allclose(res.tilt, (-0.002, -0.001), atol=2e-4)
    assert nmad((out - a.height_m)[np.isfinite(out)]) < 0.3


def test_underconstrained_fit_is_reported_not_applied():
    a, b, _ = pair((8.0, 0.0, 1.0), noise_m=0.5)
    st = np.zeros(a.grid.shape, bool)
    st[70:78, 80:88] = True  # 64 cells: far too few
    out, res = nuth_kaab(a.height_m, b.height_m, st, POST)
    assert res.status == "underconstrained" and res.reasons
    assert res.applied == "vertical" and res.shift_m[:2] == (0.0, 0.0)
    np.testing.assert_allclose(out, b.height_m + res.shift_m[2], atol=1e-3)
    # asked to apply anyway (xDEM's behaviour): applied, still flagged
    _, res2 = nuth_kaab(a.height_m, b.height_m, st, POST, CoregParams(on_underconstrained="apply"))
    assert res2.status == "underconstrained" and res2.applied == "horizontal+vertical"
    with pytest.raises(ProcessingError, match="under-constrained"):
        nuth_kaab(a.height_m, b.height_m, st, POST, CoregParams(on_underconstrained="raise"))


def test_one_sided_aspects_are_underconstrained():
    # a plane: every stable slope faces the same way → the shift along the contour is unobservable
    g = grid(80, 80)
    rr, cc = np.mgrid[0:80, 0:80].astype(float)
    rng = np.random.default_rng(0)
    ha = 1000 + 0.5 * cc * 10 + rng.normal(scale=0.2, size=rr.shape)
    hb = 1000 + 0.5 * (cc * 10 - 7) + rng.normal(scale=0.2, size=rr.shape)
    _, res = nuth_kaab(ha, hb, np.ones(g.shape, bool), POST)
    assert res.status != "ok"
    assert any("octants" in r or "bins" in r for r in res.reasons)


def test_no_stable_terrain_invents_nothing():
    a, b, _ = pair((5.0, 5.0, 3.0))
    out, res = nuth_kaab(a.height_m, b.height_m, np.zeros(a.grid.shape, bool), POST)
    assert res.status == "no_stable_terrain" and res.applied == "none"
    assert res.shift_m == (0.0, 0.0, 0.0)
    np.testing.assert_array_equal(out, b.height_m)
    with pytest.raises(ProcessingError, match="stable"):
        nuth_kaab(a.height_m, b.height_m, np.zeros(a.grid.shape, bool), POST, CoregParams(on_underconstrained="raise"))


def test_params_are_validated():
    with pytest.raises(ConfigError):
        CoregParams(on_underconstrained="maybe")
    with pytest.raises(ConfigError):
        CoregParams(min_slope_deg=50, max_slope_deg=40)
