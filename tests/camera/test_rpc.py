"""RPCModel: numba kernels vs pure-numpy references, agreement with GDAL, localization.

Non-realdata tests use a synthetic RPC (:func:`synthetic_rpc`, also used by
tests/io/test_rpc_readers.py). The realdata tests run over every RPC sample of
../shared/data (rpc_samples, s2p_pleiades, cnes_pleiades_ventoux, orthority): projection
against GDAL's RPC transformer (rasterio) on a 3-D grid spanning each RPC's validity box,
and the localization round trip on the same grid and on an image-space grid.
"""

from __future__ import annotations

import numpy as np
import pytest

from geocd.camera import RPCModel, camera_from_dict
from geocd.camera import _kernels as K
from geocd.camera.rpc import PIXEL_SHIFT, RPC00A_FROM_B, rpc00a_to_rpc00b
from geocd.errors import LocalizationError, RPCParseError
from tests.conftest import shared_data

# ---------------------------------------------------------------------------------------
# a synthetic, Pléiades-like RPC (pushbroom: sample ~ lon, line ~ -lat, small height terms)
# ---------------------------------------------------------------------------------------


def synthetic_rpc(seed: int = 0, width: int = 2000, height: int = 1600, **kw) -> RPCModel:
    """A plausible RPC00B model: near-affine with small quadratic/cubic terms and denominators."""
    rng = np.random.default_rng(seed)
    line_num = np.zeros(20)
    samp_num = np.zeros(20)
    line_num[[0, 1, 2, 3]] = [1e-3, 0.04, -1.02, -0.03]
    samp_num[[0, 1, 2, 3]] = [-2e-3, 0.99, 0.02, 0.08]
    line_num[4:] = rng.normal(0, 2e-4, 16)
    samp_num[4:] = rng.normal(0, 2e-4, 16)
    line_den = np.r_[1.0, rng.normal(0, 5e-4, 3), rng.normal(0, 2e-5, 16)]
    samp_den = np.r_[1.0, rng.normal(0, 5e-4, 3), rng.normal(0, 2e-5, 16)]
    params = dict(
        line_num=line_num,
        line_den=line_den,
        samp_num=samp_num,
        samp_den=samp_den,
        line_off=height / 2 - 0.5,
        samp_off=width / 2 - 0.5,
        lat_off=43.52,
        lon_off=5.31,
        height_off=400.0,
        line_scale=height / 2,
        samp_scale=width / 2,
        lat_scale=0.006,
        lon_scale=0.009,
        height_scale=600.0,
        width=width,
        height=height,
        err_bias=2.5,
        err_rand=0.1,
        source="synthetic",
    )
    params.update(kw)
    return RPCModel(**params)


def box_grid(m: RPCModel, n: int = 11) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lon, lat, h) on an n³ grid spanning the RPC's validity box (corners included)."""
    b = m.validity_box()
    g = np.linspace(0.0, 1.0, n)
    axes = [b[k][0] + g * (b[k][1] - b[k][0]) for k in ("lon", "lat", "h")]
    return tuple(a.ravel() for a in np.meshgrid(*axes, indexing="ij"))


def image_grid(m: RPCModel, n: int = 21, nh: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(col, row, h) spanning the RPC's image box (offset ± scale) and its height range."""
    c0, c1 = m.samp_off - abs(m.samp_scale) + PIXEL_SHIFT, m.samp_off + abs(m.samp_scale) + PIXEL_SHIFT
    r0, r1 = m.line_off - abs(m.line_scale) + PIXEL_SHIFT, m.line_off + abs(m.line_scale) + PIXEL_SHIFT
    h0, h1 = m.height_range()
    axes = [np.linspace(c0, c1, n), np.linspace(r0, r1, n), np.linspace(h0, h1, nh)]
    return tuple(a.ravel() for a in np.meshgrid(*axes, indexing="ij"))


# ---------------------------------------------------------------------------------------
# kernels vs references
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rpc() -> RPCModel:
    return synthetic_rpc()


def _random_ground(m: RPCModel, n: int, margin: float = 1.3, seed: int = 1):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-margin, margin, (3, n))
    return (m.lon_off + u[0] * m.lon_scale, m.lat_off + u[1] * m.lat_scale, m.height_off + u[2] * m.height_scale)


def test_project_kernel_matches_reference(rpc):
    lon, lat, h = _random_ground(rpc, 5000)
    col, row = rpc.project(lon, lat, h)
    s_ref, l_ref = K.project_ref(lon, lat, h, rpc._coefs, rpc._norm)
    np.testing.assert_allclose(col, s_ref + PIXEL_SHIFT, rtol=0, atol=1e-9)
    np.testing.assert_allclose(row, l_ref + PIXEL_SHIFT, rtol=0, atol=1e-9)


def test_dproj_dh_kernel_matches_reference(rpc):
    lon, lat, h = _random_ground(rpc, 2000)
    ds, dl = rpc.dproj_dh(lon, lat, h)
    ds_ref, dl_ref = K.dproj_dh_ref(lon, lat, h, rpc._coefs, rpc._norm)
    assert np.abs(ds).max() > 1e-3  # the synthetic RPC has a height effect
    np.testing.assert_allclose(ds, ds_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(dl, dl_ref, rtol=0, atol=1e-8)


def test_localize_kernel_matches_reference(rpc):
    col, row, h = image_grid(rpc, n=15, nh=3)
    lon, lat = rpc.localize(col, row, h)
    lon_ref, lat_ref = K.localize_ref(col - PIXEL_SHIFT, row - PIXEL_SHIFT, h, rpc._coefs, rpc._norm)
    assert np.all(np.isfinite(lon_ref))
    # same root; 1e-12 degree is ~0.1 micrometre
    np.testing.assert_allclose(lon, lon_ref, rtol=0, atol=1e-11)
    np.testing.assert_allclose(lat, lat_ref, rtol=0, atol=1e-11)


def test_terms_ref_order_is_rpc00b():
    L, P, H = np.array([2.0]), np.array([3.0]), np.array([5.0])
    val = {"1": 1.0, "L": 2.0, "P": 3.0, "H": 5.0}
    expected = [np.prod([val[c] for c in term]) if term != "1" else 1.0 for term in K.TERMS_RPC00B]
    np.testing.assert_array_equal(K.terms_ref(L, P, H)[:, 0], expected)


def test_rpc00a_to_rpc00b_reorders_terms():
    # a polynomial given in RPC00A order evaluates the same after conversion to RPC00B order
    a_order = (
        "1",
        "L",
        "P",
        "H",
        "LP",
        "LH",
        "PH",
        "PLH",
        "LL",
        "PP",
        "HH",
        "LLL",
        "LLP",
        "LLH",
        "LPP",
        "PPP",
        "PPH",
        "LHH",
        "PHH",
        "HHH",
    )
    rng = np.random.default_rng(3)
    coef_a = rng.normal(size=20)
    L, P, H = rng.uniform(-1, 1, (3, 50))
    val = {"1": 1.0, "L": L, "P": P, "H": H}
    terms_a = np.stack([np.ones_like(L) if t == "1" else np.prod([val[c] for c in t], axis=0) for t in a_order])
    np.testing.assert_allclose(rpc00a_to_rpc00b(coef_a) @ K.terms_ref(L, P, H), coef_a @ terms_a, atol=1e-14)
    assert sorted(RPC00A_FROM_B.tolist()) == list(range(20))
    with pytest.raises(RPCParseError):
        rpc00a_to_rpc00b(np.zeros(19))


# ---------------------------------------------------------------------------------------
# model behaviour
# ---------------------------------------------------------------------------------------
def test_localize_roundtrip_synthetic(rpc):
    for col, row, h in (image_grid(rpc), rpc.project(*box_grid(rpc)) + (box_grid(rpc)[2],)):
        lon, lat, its = rpc.localize(col, row, h, return_iterations=True)
        assert np.all(its >= 0), "100% convergence"
        c2, r2 = rpc.project(lon, lat, h)
        assert np.max(np.hypot(c2 - col, r2 - row)) <= 1e-6
        assert its.max() <= 3


def test_localize_ground_roundtrip(rpc):
    lon, lat, h = box_grid(rpc)
    col, row = rpc.project(lon, lat, h)
    lon2, lat2 = rpc.localize(col, row, h)
    np.testing.assert_allclose(lon2, lon, rtol=0, atol=1e-10)
    np.testing.assert_allclose(lat2, lat, rtol=0, atol=1e-10)


def test_localize_far_outside_uses_fallback(rpc):
    # pixels far outside the image box: the robust pass (damped Newton / multi-start) takes over
    col = np.array([-5 * rpc.samp_scale, 7 * rpc.samp_scale, rpc.samp_off])
    row = np.array([6 * rpc.line_scale, -4 * rpc.line_scale, rpc.line_off])
    h = np.array([rpc.height_off] * 3)
    lon, lat, its = rpc.localize(col, row, h, return_iterations=True)
    ok = its >= 0
    c2, r2 = rpc.project(lon[ok], lat[ok], h[ok])
    assert ok[-1] and np.max(np.hypot(c2 - col[ok], r2 - row[ok])) <= 1e-6


def test_localize_nan_and_strict(rpc):
    lon, lat, its = rpc.localize([np.nan, rpc.samp_off], [10.0, rpc.line_off], [0.0, 0.0], return_iterations=True)
    assert np.isnan(lon[0]) and its[0] == -1 and its[1] >= 0 and np.isfinite(lat[1])
    rpc.localize([np.nan], [1.0], [0.0], strict=True)  # NaN input is not a convergence failure
    # a height far beyond the model (denominator poles / folds) may not converge: strict raises
    huge = rpc.localize([1e30], [1e30], [0.0], return_iterations=True)[2]
    if huge[0] < 0:
        with pytest.raises(LocalizationError):
            rpc.localize([1e30], [1e30], [0.0], strict=True)


def test_scalar_in_scalar_out(rpc):
    c, r = rpc.project(rpc.lon_off, rpc.lat_off, rpc.height_off)
    assert np.ndim(c) == 0 and np.ndim(r) == 0
    lon, lat = rpc.localize(c, r, rpc.height_off)
    assert np.ndim(lon) == 0 and abs(lon - rpc.lon_off) < 1e-10
    assert rpc.project(np.zeros((2, 3)) + rpc.lon_off, rpc.lat_off, 0.0)[0].shape == (2, 3)


def test_cropped_is_exact(rpc):
    lon, lat, h = box_grid(rpc, 5)
    crop = rpc.cropped(123, 45, width=100, height=80)
    c0, r0 = rpc.project(lon, lat, h)
    c1, r1 = crop.project(lon, lat, h)
    np.testing.assert_allclose(c1, c0 - 123, atol=1e-9)
    np.testing.assert_allclose(r1, r0 - 45, atol=1e-9)
    assert (crop.width, crop.height) == (100, 80) and "cropped" in crop.source


def test_dict_and_rasterio_roundtrip(rpc):
    lon, lat, h = box_grid(rpc, 5)
    for other in (camera_from_dict(rpc.to_dict()), RPCModel.from_rasterio(rpc.to_rasterio(), width=2000, height=1600)):
        np.testing.assert_array_equal(other._coefs, rpc._coefs)
        np.testing.assert_array_equal(np.array(other.project(lon, lat, h)), np.array(rpc.project(lon, lat, h)))


def test_corrupt_models_raise_parse_error(rpc):
    d = rpc.to_dict()
    for bad in (
        {"line_den": [0.0] * 20},
        {"samp_scale": 0.0},
        {"lat_off": float("nan")},
        {"line_num": [1.0] * 19},
        {"samp_num": ["x"] * 20},
        {"samp_num": [0.0] * 20, "line_num": [0.0] * 20},
    ):
        with pytest.raises(RPCParseError):
            RPCModel.from_dict({**d, **bad})


def test_matches_gdal_synthetic(rpc):
    from rasterio.transform import RPCTransformer

    lon, lat, h = box_grid(rpc)
    col, row = rpc.project(lon, lat, h)
    with RPCTransformer(rpc.to_rasterio()) as tr:
        g_row, g_col = tr.rowcol(lon, lat, h, op=np.positive)
    assert np.max(np.hypot(col - g_col, row - g_row)) <= 1e-6


# ---------------------------------------------------------------------------------------
# real RPC samples (../shared/data)
# ---------------------------------------------------------------------------------------
#: every RPC sample of the shared data: (folder, file)
REAL_RPC_FILES = [
    ("rpc_samples/rpcm", "20191015_073816_ssc1d3_0011_basic_l1a_panchromatic_dn_RPC.TXT"),
    ("rpc_samples/rpcm", "JAX_068_001_RGB.json"),
    ("rpc_samples/rpcm", "rpc_IKONOS.txt"),
    ("rpc_samples/rpcm", "rpc_PLANET_L1A.txt"),
    ("rpc_samples/rpcm", "rpc_PLANET_L1B.txt"),
    ("rpc_samples/rpcm", "rpc_PLEIADES.xml"),
    ("rpc_samples/rpcm", "rpc_SPOT6.xml"),
    ("rpc_samples/rpcm", "rpc_WV1.xml"),
    ("rpc_samples/rpcm", "rpc_WV2.xml"),
    ("rpc_samples/rpcm", "rpc_WV3.xml"),
    ("rpc_samples/shareloc", "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.geom"),
    ("rpc_samples/shareloc", "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.tif"),
    ("rpc_samples/shareloc", "RPC_PHR1B_P_201709281038045_SEN_PRG_FC_178608-001.XML"),
    ("rpc_samples/shareloc", "RPC_PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.XML"),
    ("rpc_samples/shareloc", "wv3_20.NTF"),
    ("rpc_samples/shareloc", "wv3_30.NTF"),
    ("s2p_pleiades/input_pair", "img_01.tif"),
    ("s2p_pleiades/input_pair", "img_02.tif"),
    ("s2p_pleiades/input_triplet", "img_01.tif"),
    ("s2p_pleiades/input_triplet", "img_02.tif"),
    ("s2p_pleiades/input_triplet", "img_03.tif"),
    ("cnes_pleiades_ventoux", "left_image.geom"),
    ("cnes_pleiades_ventoux", "right_image.geom"),
    ("cnes_pleiades_ventoux", "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML"),
    ("orthority_baviaans_aerial_qb2/rpc", "qb2_basic1b.tif"),
    ("orthority_baviaans_aerial_qb2/rpc", "rpc_param.yaml"),
]
_IDS = [f"{d.split('/')[0]}/{f}" for d, f in REAL_RPC_FILES]


@pytest.fixture(scope="module")
def gdal_stats() -> dict:
    """Collects per-sample figures; printed at the end of the module (pytest -s shows them)."""
    stats: dict = {}
    yield stats
    if stats:
        print("\nsample | max |geocd - GDAL| px | round trip max px (ground grid, image grid) | max iterations")
        for k, v in stats.items():
            print(
                f"{k} | {v.get('gdal', float('nan')):.1e} | {v.get('rt_ground', float('nan')):.1e}, "
                f"{v.get('rt_image', float('nan')):.1e} | {v.get('iters', '-')}"
            )


@pytest.mark.realdata
@pytest.mark.parametrize("folder,name", REAL_RPC_FILES, ids=_IDS)
def test_real_rpc_matches_gdal(folder, name, gdal_stats):
    from rasterio.transform import RPCTransformer

    from geocd.io.rpc import read_rpc

    m = read_rpc(shared_data(folder, name))
    lon, lat, h = box_grid(m)
    col, row = m.project(lon, lat, h)
    with RPCTransformer(m.to_rasterio()) as tr:  # GDAL evaluates the same 90 numbers
        g_row, g_col = tr.rowcol(lon, lat, h, op=np.positive)
    err = np.hypot(col - g_col, row - g_row)
    gdal_stats.setdefault(f"{folder}/{name}", {})["gdal"] = float(err.max())
    assert err.max() <= 1e-3


@pytest.mark.realdata
@pytest.mark.parametrize("folder,name", REAL_RPC_FILES, ids=_IDS)
def test_real_rpc_localization_roundtrip(folder, name, gdal_stats):
    from geocd.io.rpc import read_rpc

    m = read_rpc(shared_data(folder, name))
    lon, lat, h = box_grid(m)
    col, row = m.project(lon, lat, h)
    st = gdal_stats.setdefault(f"{folder}/{name}", {})
    iters = []
    for key, (c, r, hh) in (("rt_ground", (col, row, h)), ("rt_image", image_grid(m))):
        lon2, lat2, its = m.localize(c, r, hh, return_iterations=True)
        assert np.all(its >= 0), f"{key}: {np.sum(its < 0)} of {its.size} samples did not converge"
        c2, r2 = m.project(lon2, lat2, hh)
        st[key] = float(np.max(np.hypot(c2 - c, r2 - r)))
        assert st[key] <= 1e-6
        iters.append(int(its.max()))
    st["iters"] = max(iters)


@pytest.mark.realdata
def test_real_s2p_rpc_matches_gdal_on_image_tags():
    """GDAL's transformer built from the file's own tags (not from our model) agrees too."""
    import rasterio
    from rasterio.transform import RPCTransformer

    from geocd.io.rpc import load_rpc_for_image

    path = shared_data("s2p_pleiades", "input_pair", "img_01.tif")
    m = load_rpc_for_image(path)
    lon, lat, h = box_grid(m, 9)
    with rasterio.open(path) as ds, RPCTransformer(ds.rpcs) as tr:
        g_row, g_col = tr.rowcol(lon, lat, h, op=np.positive)
        # and GDAL's localization at a tight threshold lands on our ground point
        col, row = m.project(lon, lat, h)
    with RPCTransformer(ds.rpcs, RPC_PIXEL_ERROR_THRESHOLD=1e-8) as tr:
        g_lon, g_lat = tr.xy(row, col, h, offset="ul")
    assert np.max(np.hypot(col - g_col, row - g_row)) <= 1e-6
    ok = np.isfinite(g_lon)
    assert ok.mean() > 0.9
    my_lon, my_lat = m.localize(col, row, h)
    assert np.max(np.abs(np.asarray(g_lon)[ok] - my_lon[ok])) < 1e-8
    assert np.max(np.abs(np.asarray(g_lat)[ok] - my_lat[ok])) < 1e-8


def _crop_far_from_centre(rpc):
    """A 300² crop whose corner lies ~0.8 of the validity box's half-width from its centre, as a
    vendor crop of a large scene (WorldView-3 tiles in NITF) has it."""
    return rpc.cropped(rpc.samp_off + 0.8 * rpc.samp_scale - 300, rpc.line_off + 0.8 * rpc.line_scale - 300, 300, 300)


def test_reference_localizer_converges_on_a_crop_far_from_the_box_centre(rpc):
    crop = _crop_far_from_centre(rpc)
    col, row, h = image_grid(crop, n=7, nh=3)
    lon, lat = crop.localize(col, row, h)
    lon_ref, lat_ref = crop.localize_reference(col, row, h)
    assert np.all(np.isfinite(lon_ref)) and np.all(np.isfinite(lat_ref))
    np.testing.assert_allclose(lon_ref, lon, rtol=0, atol=1e-10)
    np.testing.assert_allclose(lat_ref, lat, rtol=0, atol=1e-10)
    # geocd info's footprint (numpy paths, no compile) is the kernels' footprint
    h0 = float(np.mean(crop.height_range()))
    a, b = crop.footprint(h0, reference=True), crop.footprint(h0)
    assert a.symmetric_difference(b).area < 1e-6 * b.area


@pytest.mark.realdata
def test_info_footprint_of_worldview3_crops_in_nitf():
    """The two 500² WorldView-3 NITF crops (RPC00B TRE; ../shared/data/rpc_samples/shareloc): the numpy
    localizer of `geocd info` reaches every corner and agrees with the kernels (was: "footprint: unavailable")."""
    from geocd.info import camera_summary
    from geocd.io.cameras import load_camera

    for name in ("wv3_20.NTF", "wv3_30.NTF"):
        cam = load_camera(shared_data("rpc_samples", "shareloc", name))
        col, row, h = image_grid(cam, n=7, nh=3)
        lon, lat = cam.localize(col, row, h)
        lon_ref, lat_ref = cam.localize_reference(col, row, h)
        np.testing.assert_allclose(lon_ref, lon, rtol=0, atol=1e-10)
        np.testing.assert_allclose(lat_ref, lat, rtol=0, atol=1e-10)
        d = camera_summary(cam)
        assert "footprint_error" not in d, d
        assert 0.02 < d["footprint_area_km2"] < 0.04 and 0.3 < min(d["gsd_m"]) < 0.4


def test_summary_localizer_falls_back_on_the_methods_localizer(rpc, monkeypatch):
    """Where the numpy path does not converge, `geocd info`'s footprint takes the methods' localizer
    (the footprint and the GSD never say "unavailable" where the methods localize)."""
    from geocd.info import camera_summary

    crop = _crop_far_from_centre(rpc)
    real_ref = RPCModel.localize_reference

    def missing_half(self, col, row, h):  # a numpy path that misses every other point
        lon, lat = real_ref(self, col, row, h)
        lon, lat = np.array(lon, float), np.array(lat, float)
        lon.reshape(-1)[::2] = np.nan
        lat.reshape(-1)[::2] = np.nan
        return lon, lat

    monkeypatch.setattr(RPCModel, "localize_reference", missing_half)
    h0 = float(np.mean(crop.height_range()))
    a, b = crop.footprint(h0, reference=True), crop.footprint(h0)
    assert a.symmetric_difference(b).area < 1e-6 * b.area
    d = camera_summary(crop)
    assert "footprint_error" not in d and d["footprint_area_km2"] > 0


@pytest.mark.realdata
def test_info_footprint_of_a_worldview3_crop_with_large_offsets():
    """A 500² crop of the WorldView-3 RPC far from its scene (sample offset 30864, line offset 124505; GeoTIFF
    RPC tags as a vendor crop carries them): the numpy path alone misses corners the kernels reach; `geocd info`'s
    footprint is the kernels' footprint (was: "footprint: unavailable (image corners ... do not reach height)")."""
    from geocd.info import camera_summary
    from geocd.io.cameras import load_camera

    cam = load_camera(shared_data("rpc_samples", "shareloc", "wv3_20.NTF"))
    crop = cam.cropped(-10115, -107010, 500, 500)
    c = crop.image_corners()
    h = np.full(4, crop.height_off)
    lon_ref, _ = crop.localize_reference(c[:, 0], c[:, 1], h)
    lon, lat = crop.localize(c[:, 0], c[:, 1], h)
    assert np.all(np.isfinite(lon)) and not np.all(np.isfinite(lon_ref))  # the case of the issue
    lon_s, lat_s = crop.localize_summary(c[:, 0], c[:, 1], h)
    np.testing.assert_allclose(lon_s, lon, rtol=0, atol=1e-9)
    np.testing.assert_allclose(lat_s, lat, rtol=0, atol=1e-9)
    a, b = crop.footprint(crop.height_off, reference=True), crop.footprint(crop.height_off)
    assert a.symmetric_difference(b).area < 1e-6 * b.area
    d = camera_summary(crop)
    assert "footprint_error" not in d, d
