"""Real-data checks on orthority's Baviaans set: 4 NGI aerial frames (2015), a DEM, a QuickBird-2 RPC image (2003).

What is measured (``python -m tests.camera.test_baviaans`` prints every figure on a denser sample):

* **Frame ↔ frame.** For DEM posts seen by two frames A and B, both images are
  orthorectified onto a small local grid (5 m cells) around the post with the
  frame cameras and the DEM; B's ortho patch is searched for A's by normalised
  cross-correlation (sub-cell parabola peak). With correct cameras and DEM the
  best shift is zero; the shift, mapped into B's pixels through B's camera, is
  the tie-point residual (pixels). Ortho patches make the comparison
  independent of the strips' 180° kappa difference.
* **QB2 RPC ↔ GCPs.** ``rpc/gcps.geojson`` gives 5 surveyed points (orthority
  pixel ``ji`` with pixel centres at integers = geocd ``col - 0.5``, and
  lon/lat/ellipsoidal height). The residual is the RPC's bias.
* **QB2 ↔ frames.** The same ortho-patch matching between the QB2 image (RPC)
  and each frame gives the ground disagreement in metres, raw and after
  removing the GCP bias (an image-space shift of the RPC, :meth:`RPCModel.cropped`).

Datums: ``ngi/dem.tif`` holds EGM2008 heights and the frames' z are in the same
datum. The EGM2008 grid is not on this machine, so the DEM is converted to
ellipsoidal heights with EGM96 (``allow_substitute=True`` / the cameras'
``allow_geoid_substitute``). For the frames the substitute cancels (camera z and
DEM share it). For QB2 a height error of 1 m moves its projection by ~0.04 px
(~0.27 m on the ground); EGM2008 − EGM96 is typically below 1 m away from high
mountains (not measurable here without the EGM2008 grid).
"""

from __future__ import annotations

import itertools
import json
import warnings
from dataclasses import dataclass

import numpy as np
import pytest

from geocd.camera.frame import FrameCamera
from geocd.camera.rpc import RPCModel
from geocd.geodesy import find_geoid_grid
from tests.conftest import shared_data

pytestmark = [
    pytest.mark.realdata,
    pytest.mark.skipif(find_geoid_grid("egm96") is None, reason="EGM96 geoid grid (egm96_15.gtx) not installed"),
    pytest.mark.filterwarnings("ignore:EGM2008 geoid grid not found"),
]

FOLDER = "orthority_baviaans_aerial_qb2"


@dataclass
class Scene:
    cams: dict[str, FrameCamera]
    images: dict[str, np.ndarray]  # grey float, NaN outside the valid mask
    rpc: RPCModel
    qb2: np.ndarray
    dem_h: np.ndarray  # ellipsoidal heights (float64)
    dem_grid: object
    dem_datum: str
    gcp_ji: np.ndarray  # (n, 2) orthority pixels
    gcp_llh: np.ndarray  # (n, 3) lon, lat, ellipsoidal h


def load_scene() -> Scene:
    import rasterio

    from geocd.io.frame import read_orthority_cameras
    from geocd.io.raster import read_dem

    root = shared_data(FOLDER)
    names = sorted(p.stem for p in (root / "ngi").glob("3324c_*_RGB.tif"))
    with rasterio.open(root / "ngi" / f"{names[0]}.tif") as ds:
        crs = ds.crs  # orthority takes the EO CRS from the images ("Lo25 WGS84")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cams = read_orthority_cameras(
            root / "io/ngi_int_param.yaml",
            root / "ngi/camera_pos_ori.txt",
            crs=crs,
            vertical_datum="egm2008",
            allow_geoid_substitute=True,
        )
        dem = read_dem(root / "ngi/dem.tif")
        dem_e = dem.to_ellipsoidal(allow_substitute=True)
    images = {}
    for n in names:
        with rasterio.open(root / "ngi" / f"{n}.tif") as ds:
            rgb = ds.read().astype(np.float64)
            mask = ds.read_masks(1) > 0
        grey = rgb.mean(axis=0)
        grey[~mask] = np.nan
        images[n] = grey
    with rasterio.open(root / "rpc/qb2_basic1b.tif") as ds:
        rpc = RPCModel.from_rasterio(ds.rpcs, width=ds.width, height=ds.height, source="qb2_basic1b.tif tags")
        qb2 = ds.read(1).astype(np.float64)
    g = json.loads((root / "rpc/gcps.geojson").read_text())
    ji = np.array([f["properties"]["ji"] for f in g["features"]], float)
    llh = np.array([f["geometry"]["coordinates"] for f in g["features"]], float)
    return Scene(cams, images, rpc, qb2, dem_e.height_m.astype(np.float64), dem.grid, dem.vertical_datum, ji, llh)


@pytest.fixture(scope="module")
def scene() -> Scene:
    return load_scene()


# ------------------------------------------------------------------------------------------
# ortho-patch matching
# ------------------------------------------------------------------------------------------
def _bilinear(img: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Sample at geocd pixel coordinates (corner origin); NaN outside."""
    from scipy.ndimage import map_coordinates

    return map_coordinates(img, [row - 0.5, col - 0.5], order=1, cval=np.nan, mode="constant")


def dem_height(sc: Scene, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    row, col = sc.dem_grid.rowcol(x, y)
    return _bilinear(sc.dem_h, col, row)


def ortho(sc: Scene, cam, img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    col, row = cam.ground_projector(x, y, sc.dem_grid.crs).project(dem_height(sc, x, y))
    return _bilinear(img, col, row)


def image_position(sc: Scene, cam, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cam.ground_projector(x, y, sc.dem_grid.crs).project(dem_height(sc, x, y))


def inside(sc: Scene, cam, x, y, margin: float = 40.0) -> np.ndarray:
    c, r = image_position(sc, cam, x, y)
    return (c > margin) & (c < cam.width - margin) & (r > margin) & (r < cam.height - margin)


def ncc_surface(tpl: np.ndarray, big: np.ndarray) -> np.ndarray:
    """NCC of templates (P, n, n) at every offset inside windows (P, n + 2S, n + 2S) → (P, 2S+1, 2S+1).

    Correlation by FFT, window means and energies by summed-area tables.
    """
    from scipy.signal import fftconvolve

    n = tpl.shape[1]
    a = tpl - tpl.mean(axis=(1, 2), keepdims=True)
    an = np.sqrt((a * a).sum(axis=(1, 2)))[:, None, None]
    num = fftconvolve(big, a[:, ::-1, ::-1], mode="valid", axes=(1, 2))

    def box(v):
        c = np.pad(v.cumsum(axis=1).cumsum(axis=2), ((0, 0), (1, 0), (1, 0)))
        return c[:, n:, n:] - c[:, :-n, n:] - c[:, n:, :-n] + c[:, :-n, :-n]

    s1, s2 = box(big), box(big * big)
    var = np.maximum(s2 - s1 * s1 / (n * n), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / (an * np.sqrt(var))


def ncc_surface_ref(tpl: np.ndarray, big: np.ndarray) -> np.ndarray:
    """Direct loop over offsets (reference for :func:`ncc_surface`)."""
    p, n, _ = tpl.shape
    k = big.shape[1] - n + 1
    a = tpl - tpl.mean(axis=(1, 2), keepdims=True)
    an = np.sqrt((a * a).sum(axis=(1, 2)))
    out = np.empty((p, k, k))
    for dy in range(k):
        for dx in range(k):
            b = big[:, dy : dy + n, dx : dx + n]
            b = b - b.mean(axis=(1, 2), keepdims=True)
            out[:, dy, dx] = (a * b).sum(axis=(1, 2)) / (an * np.sqrt((b * b).sum(axis=(1, 2))))
    return out


def subcell_peak(s: np.ndarray):
    """Peak of NCC surfaces (P, K, K): (dy, dx) from the centre with parabola refinement, value, interior."""
    p, k, _ = s.shape
    flat = np.nan_to_num(s, nan=-2.0).reshape(p, -1)
    idx = flat.argmax(axis=1)
    iy, ix = np.unravel_index(idx, (k, k))
    peak = flat[np.arange(p), idx]
    interior = (iy > 0) & (iy < k - 1) & (ix > 0) & (ix < k - 1)
    iy2, ix2, ii = np.clip(iy, 1, k - 2), np.clip(ix, 1, k - 2), np.arange(p)

    def parabola(m, c, q):
        d = m - 2 * c + q
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(d < 0, 0.5 * (m - q) / d, 0.0)

    oy = parabola(s[ii, iy2 - 1, ix2], s[ii, iy2, ix2], s[ii, iy2 + 1, ix2])
    ox = parabola(s[ii, iy2, ix2 - 1], s[ii, iy2, ix2], s[ii, iy2, ix2 + 1])
    return iy + oy - k // 2, ix + ox - k // 2, peak, interior


@dataclass
class Matches:
    x: np.ndarray  # ground posts (EO CRS), metres
    y: np.ndarray
    shift_x: np.ndarray  # where B's ortho shows A's feature, relative to the post (m, east)
    shift_y: np.ndarray  # (m, north)
    peak: np.ndarray  # NCC at the peak
    ok: np.ndarray  # textured, interior peak, NCC above the threshold


def match_ortho(
    sc: Scene,
    cam_a,
    img_a,
    cam_b,
    img_b,
    x0,
    y0,
    *,
    post_m: float = 5.0,
    half: int = 12,
    search: int = 6,
    min_ncc: float = 0.7,
    min_std: float = 3.0,
) -> Matches:
    off = np.arange(-half - search, half + search + 1) * post_m
    X = np.broadcast_to(x0[:, None, None] + off[None, None, :], (x0.size, off.size, off.size))
    Y = np.broadcast_to(y0[:, None, None] - off[None, :, None], (x0.size, off.size, off.size))
    big = ortho(sc, cam_b, img_b, X, Y)
    core = (slice(None), slice(search, -search), slice(search, -search))
    tpl = ortho(sc, cam_a, img_a, X[core], Y[core])
    usable = (
        np.all(np.isfinite(tpl), axis=(1, 2))
        & np.all(np.isfinite(big), axis=(1, 2))
        & (np.std(tpl, axis=(1, 2)) > min_std)
    )
    dy, dx, peak, interior = subcell_peak(ncc_surface(tpl[usable], big[usable]))
    ok = interior & (peak >= min_ncc)
    return Matches(x0[usable], y0[usable], dx * post_m, -dy * post_m, peak, ok)


def residual_px(sc: Scene, cam_b, m: Matches) -> np.ndarray:
    """Tie-point residuals in B's pixels (accepted matches only)."""
    x, y = m.x[m.ok], m.y[m.ok]
    c0, r0 = image_position(sc, cam_b, x, y)
    c1, r1 = image_position(sc, cam_b, x + m.shift_x[m.ok], y + m.shift_y[m.ok])
    return np.hypot(c1 - c0, r1 - r0)


def dem_posts(sc: Scene, step: int) -> tuple[np.ndarray, np.ndarray]:
    x, y = sc.dem_grid.xy()
    return x[::step, ::step].ravel(), y[::step, ::step].ravel()


def frame_pair_residuals(sc: Scene, step: int = 3, cams: dict | None = None) -> dict[tuple[str, str], np.ndarray]:
    cams = cams or sc.cams
    xs, ys = dem_posts(sc, step)
    out = {}
    for a, b in itertools.combinations(sorted(cams), 2):
        sel = inside(sc, cams[a], xs, ys) & inside(sc, cams[b], xs, ys)
        m = match_ortho(sc, cams[a], sc.images[a], cams[b], sc.images[b], xs[sel], ys[sel])
        out[(a, b)] = residual_px(sc, cams[b], m)
    return out


def gcp_residuals(sc: Scene) -> np.ndarray:
    """(n, 2) RPC − GCP in geocd pixels (GCP ji are orthority pixels: centres at integers)."""
    c, r = sc.rpc.project(sc.gcp_llh[:, 0], sc.gcp_llh[:, 1], sc.gcp_llh[:, 2])
    return np.column_stack([c - (sc.gcp_ji[:, 0] + 0.5), r - (sc.gcp_ji[:, 1] + 0.5)])


def qb2_frame_shifts(sc: Scene, rpc: RPCModel, step: int, names=None) -> np.ndarray:
    """(n, 2) ground disagreements (m, east/north) between QB2 and frames, accepted matches pooled."""
    xs, ys = dem_posts(sc, step)
    out = []
    for n in names or sorted(sc.cams):
        cam = sc.cams[n]
        sel = inside(sc, cam, xs, ys) & inside(sc, rpc, xs, ys)
        m = match_ortho(
            sc, rpc, sc.qb2, cam, sc.images[n], xs[sel], ys[sel], post_m=5.0, half=12, search=8, min_ncc=0.6
        )
        out.append(np.column_stack([m.shift_x[m.ok], m.shift_y[m.ok]]))
    return np.concatenate(out)


def rpc_bias_ground_m(sc: Scene, bias_px: np.ndarray) -> np.ndarray:
    """Ground displacement (m, east/north) that an image-space RPC bias produces, at the scene centre."""
    from geocd.geodesy import from_lonlat

    lon, lat, h = sc.rpc.lon_off, sc.rpc.lat_off, float(np.nanmedian(sc.dem_h))
    d = 1e-4
    c, r = sc.rpc.project([lon, lon + d, lon], [lat, lat, lat + d], h)
    x, y = from_lonlat([lon, lon + d, lon], [lat, lat, lat + d], sc.dem_grid.crs)
    # Jacobian d(col, row)/d(x, y) in the DEM's projected CRS
    J = np.linalg.solve(
        np.array([[x[1] - x[0], x[2] - x[0]], [y[1] - y[0], y[2] - y[0]]]).T,
        np.array([[c[1] - c[0], c[2] - c[0]], [r[1] - r[0], r[2] - r[0]]]).T,
    ).T
    return np.linalg.solve(J, bias_px)


# ------------------------------------------------------------------------------------------
# tests
# ------------------------------------------------------------------------------------------
def test_ncc_helpers():
    rng = np.random.default_rng(0)
    big = rng.normal(size=(3, 31, 31)).cumsum(axis=1)
    tpl = big[:, 5:26, 7:28] * 2.0 + 1.0  # true offset (dy, dx) = (0, +2) from the centre (5, 5)
    s = ncc_surface(tpl, big)
    np.testing.assert_allclose(s, ncc_surface_ref(tpl, big), atol=1e-9)
    dy, dx, peak, interior = subcell_peak(s)
    np.testing.assert_allclose(dy, 0.0, atol=0.05)  # parabola refinement: a few hundredths of a cell
    np.testing.assert_allclose(dx, 2.0, atol=0.05)
    assert np.all(peak > 0.999) and np.all(interior)


def test_dem_datum_is_handled(scene):
    assert scene.dem_datum == "egm2008"
    for cam in scene.cams.values():
        assert cam.vertical_datum == "egm2008" and cam.allow_geoid_substitute
    # the EGM96 substitute undulation here is ~28.3 m
    lon, lat, _ = next(iter(scene.cams.values())).position_lonlat_h()
    assert 27.0 < float(next(iter(scene.cams.values())).undulation(lon, lat)) < 30.0


@pytest.mark.slow
def test_frames_agree_across_overlaps(scene):
    res = frame_pair_residuals(scene, step=4)  # every 4th DEM post (96 m); the report uses every 3rd
    pooled = np.concatenate(list(res.values()))
    for pair, r in res.items():
        print(
            f"{pair[0][-8:]}-{pair[1][-8:]}: n={r.size} median={np.median(r):.2f} px p90={np.percentile(r, 90):.2f} px"
        )
        assert r.size >= 60, pair
        assert np.median(r) < 0.5, pair
    print(f"pooled: n={pooled.size} median={np.median(pooled):.2f} px p90={np.percentile(pooled, 90):.2f} px")
    assert pooled.size > 1500
    assert np.median(pooled) < 0.3 and np.percentile(pooled, 90) < 1.0


def test_frame_check_detects_a_one_pixel_error(scene):
    """Negative control: the same check flags a 1-pixel principal-point error in one frame."""
    a, b = sorted(scene.cams)[:2]  # 05_0182 and 05_0184, one strip
    cams = dict(scene.cams)
    cx, cy = cams[b].principal_point_px
    good = frame_pair_residuals(scene, step=4, cams={a: cams[a], b: cams[b]})[(a, b)]
    cams[b] = cams[b].replace(principal_point_px=(cx + 1.0, cy))
    bad = frame_pair_residuals(scene, step=4, cams={a: cams[a], b: cams[b]})[(a, b)]
    print(f"control: median {np.median(good):.2f} px → {np.median(bad):.2f} px with a 1 px error")
    assert np.median(bad) > 0.8 > 0.3 > np.median(good)


def test_qb2_rpc_against_gcps(scene):
    d = gcp_residuals(scene)
    mean, sd = d.mean(axis=0), d.std(axis=0)
    print(
        f"QB2 RPC − GCP: mean ({mean[0]:.2f}, {mean[1]:.2f}) px, |mean| {np.hypot(*mean):.2f} px, "
        f"sd ({sd[0]:.2f}, {sd[1]:.2f}) px, n={len(d)}"
    )
    # a pure bias of ~3.6 px: the RPC is not refined; the scatter about it is small
    assert 3.0 < np.hypot(*mean) < 4.5
    assert np.all(sd < 0.2)


@pytest.mark.slow
def test_qb2_and_frames_agree_on_the_ground(scene):
    bias_px = gcp_residuals(scene).mean(axis=0)
    expected = rpc_bias_ground_m(scene, bias_px)
    raw = qb2_frame_shifts(scene, scene.rpc, step=6, names=sorted(scene.cams)[::3])
    med_raw = np.median(raw, axis=0)
    corrected_rpc = scene.rpc.cropped(bias_px[0], bias_px[1], scene.rpc.width, scene.rpc.height)
    cor = qb2_frame_shifts(scene, corrected_rpc, step=6, names=sorted(scene.cams)[::3])
    med_cor = np.median(cor, axis=0)
    mag = np.hypot(cor[:, 0], cor[:, 1])
    print(
        f"QB2 vs frames raw: median shift ({med_raw[0]:.1f}, {med_raw[1]:.1f}) m (n={len(raw)}); "
        f"GCP bias predicts ({expected[0]:.1f}, {expected[1]:.1f}) m"
    )
    print(
        f"QB2 (GCP-bias corrected) vs frames: median shift ({med_cor[0]:.2f}, {med_cor[1]:.2f}) m, "
        f"|shift| median {np.median(mag):.2f} m, p90 {np.percentile(mag, 90):.2f} m (n={len(cor)})"
    )
    assert len(raw) > 300 and len(cor) > 300
    # the frames (NGI aerial triangulation) and the GCPs measure the same RPC bias, within 3 m
    assert np.hypot(*(med_raw - expected)) < 3.0
    # after removing it, QB2 and the frames agree to about a QB2 pixel (~6.5 m)
    assert np.hypot(*med_cor) < 1.5
    assert np.median(mag) < 4.0


# ------------------------------------------------------------------------------------------
# full report: python -m tests.camera.test_baviaans
# ------------------------------------------------------------------------------------------
def report() -> None:  # pragma: no cover - manual
    warnings.simplefilter("ignore")
    sc = load_scene()
    print(f"DEM datum {sc.dem_datum} → ellipsoidal with the EGM96 substitute (EGM2008 grid absent)")
    res = frame_pair_residuals(sc, step=3)
    for (a, b), r in res.items():
        print(
            f"frames {a[-8:]} / {b[-8:]}: n={r.size:5d}  median {np.median(r):.2f} px  "
            f"p90 {np.percentile(r, 90):.2f} px"
        )
    pooled = np.concatenate(list(res.values()))
    print(f"frames pooled: n={pooled.size}  median {np.median(pooled):.2f} px  p90 {np.percentile(pooled, 90):.2f} px")
    d = gcp_residuals(sc)
    for row in d:
        print(f"GCP residual RPC − GCP: ({row[0]:+.2f}, {row[1]:+.2f}) px")
    bias = d.mean(axis=0)
    xs, ys = dem_posts(sc, 3)
    from geocd.geodesy import to_lonlat

    lon, lat = to_lonlat(xs, ys, sc.dem_grid.crs)
    h = dem_height(sc, xs, ys)
    n_geoid = float(np.nanmedian(sc.cams[sorted(sc.cams)[0]].undulation(lon, lat)))
    c1, r1 = sc.rpc.project(lon, lat, h)
    c0, r0 = sc.rpc.project(lon, lat, h - n_geoid)
    shift = np.hypot(c1 - c0, r1 - r0)
    print(
        f"datum: N = {n_geoid:.2f} m (EGM96); ignoring it would move QB2 projections by a median "
        f"{np.nanmedian(shift):.2f} px; frame heights share the datum of the camera z"
    )
    print(f"GCP bias ({bias[0]:.2f}, {bias[1]:.2f}) px = {rpc_bias_ground_m(sc, bias).round(1)} m on the ground")
    for label, rpc in (
        ("raw RPC", sc.rpc),
        ("GCP-bias-corrected RPC", sc.rpc.cropped(bias[0], bias[1], sc.rpc.width, sc.rpc.height)),
    ):
        v = qb2_frame_shifts(sc, rpc, step=3)
        mag = np.hypot(v[:, 0], v[:, 1])
        med = np.median(v, axis=0)
        print(
            f"QB2 ({label}) vs 4 frames: n={len(v)}  median shift ({med[0]:.2f}, {med[1]:.2f}) m  "
            f"|shift| median {np.median(mag):.2f} m  p90 {np.percentile(mag, 90):.2f} m"
        )


if __name__ == "__main__":  # pragma: no cover
    report()
