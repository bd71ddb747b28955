"""A large two-epoch RPC stereo scene with known changes, made in minutes with bounded memory (scale tests).

:func:`make_stereo_scene` writes, for an AOI of ``cells`` × ``cells`` cells:

* **World** — procedural terrain (value-noise octaves, 2 km down to 40 m, ~30 m of relief) plus
  flat-roofed box buildings on a jittered 32 m lattice (one slot in two or so built, each with its
  own size, height 4–18 m and roof tone, drawn from a hash of the slot: any window is the same
  whatever the tiling). Epoch B demolishes a share of the buildings and builds new ones on empty
  slots. Heights are WGS84 ellipsoidal. The DSM of a window is
  :func:`geocd.synth._kernels.dem_window` (the terrain + boxes kernel of :mod:`geocd.synth.bigdem`).
* **Views** — physical pushbroom cameras at orbital distance (:func:`geocd.synth.sensors.make_pushbroom`,
  the cameras of ``geocd synth``), each with an RPC00B fitted to it (:func:`geocd.camera.rpc_fit.fit_rpc`;
  the fit's check-grid residual is recorded) and written into the image's GeoTIFF RPC tags.
* **Rendering by inverse mapping** — each image block's pixel rays (localized by the physical camera at
  the top and the bottom of the scene's height band on a 16-px lattice, interpolated bilinearly in
  between: a pushbroom's rays vary smoothly, < 1e-3 px over 16 px) are marched down through a DSM
  window sampled at half the AOI posting (:func:`geocd.synth._kernels.march_dsm`: steps of a
  quarter cell horizontally, bilinear surface, linear refinement of the first crossing). The first
  crossing from above is what the pixel sees, so **occlusions are exact up to the DSM sampling**:
  a roof hides the ground behind it and walls facing the sensor are seen (as the steep faces of the
  bilinear DSM). The hit point's albedo is a procedural texture of its map coordinates (ground,
  roofs with a per-building tone, darker walls). No cast shadows, uniform light. Then a Gaussian
  PSF, gain/haze per view, shot + read noise, 11-bit counts (:func:`geocd.synth.render.to_sensor_counts`).
  Blocks of ``block`` pixels (plus a 4-px halo for the PSF) are rendered on ``workers`` threads
  (the kernels release the GIL) and written into a tiled GeoTIFF window by window: memory is
  bounded by a few blocks whatever the size.
* **Truth** on the AOI grid (cell centres, exact, noise-free): ``dsm_A.tif``, ``dsm_B.tif``,
  ``dh.tif`` (B − A), ``change_mask.tif`` (1 where |dh| > ``change_threshold_m``), ``dem_prior.tif``
  (the bare terrain at 2 m: the stereo search prior), ``buildings.gpkg`` (every building of either
  epoch with ``status`` unchanged / demolished / new and its height) and ``truth.json``.
* ``scene.yaml`` — a geocd manifest (``geocd stereo``/``geocd run`` and the tiled runs read it).
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from ..errors import ConfigError
from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress
from . import _kernels as K

SCALES_M = np.array([2000.0, 800.0, 300.0, 100.0, 40.0])
AMPS_M = np.array([14.0, 6.0, 2.5, 0.8, 0.25])
SLOT_M = 32.0


@dataclass(frozen=True)
class StereoSceneParams:
    """Parameters of :func:`make_stereo_scene` (sizes in cells, lengths in metres, angles in degrees).

    ``views_a`` / ``views_b``: (along, across) off-nadir angles of each epoch's views.
    ``event_radius_m``: ``None`` (default) — buildings are demolished and built anywhere in the AOI;
    a radius — only buildings whose centre lies within this distance of the event centre change (a
    local event: an earthquake's or a storm's footprint, a redevelopment zone), at the same
    ``demolished_fraction`` / ``new_fraction`` there; every building outside stands in both epochs
    unchanged and no new one is built. ``event_centre_m``: the event centre as (east, north)
    metres from the AOI centre. The buildings themselves (places, sizes, heights) are the same.
    """

    cells: int = 2500
    posting_m: float = 0.5
    seed: int = 0
    lon0: float = 3.87
    lat0: float = 43.61
    base_m: float = 100.0
    built_fraction: float = 0.5
    demolished_fraction: float = 0.04
    new_fraction: float = 0.04
    change_threshold_m: float = 1.0
    views_a: tuple[tuple[float, float], ...] = ((-9.0, 2.0), (9.0, 2.0))
    views_b: tuple[tuple[float, float], ...] = ((-7.0, -3.0), (11.0, -3.0))
    altitude_m: float = 620e3
    heading_deg: float = 192.0
    event_radius_m: float | None = None
    event_centre_m: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if self.cells < 64 or self.posting_m <= 0:
            raise ConfigError(f"cells ≥ 64 and a positive posting are required, got {self.cells}, {self.posting_m}")
        if self.event_radius_m is not None and not (math.isfinite(self.event_radius_m) and self.event_radius_m > 0):
            raise ConfigError(f"event_radius_m must be a positive number of metres or None, got {self.event_radius_m}")
        if len(self.event_centre_m) != 2 or not all(math.isfinite(float(v)) for v in self.event_centre_m):
            raise ConfigError(
                f"event_centre_m must be (east, north) metres from the AOI centre, got {self.event_centre_m}"
            )
        if len(self.views_a) < 2 or len(self.views_b) < 2:
            raise ConfigError("each epoch needs two views or more (a stereo pair)")

    def grid(self) -> AOIGrid:
        """The AOI grid: ``cells`` × ``cells`` cells centred on (lon0, lat0), in its UTM zone."""
        from ..geodesy import from_lonlat, utm_crs_for

        crs = utm_crs_for(self.lon0, self.lat0)
        e, n = from_lonlat(self.lon0, self.lat0, crs)
        half = 0.5 * self.cells * self.posting_m
        x0 = float(np.round(float(e) - half))
        y0 = float(np.round(float(n) + half))
        p = self.posting_m
        return AOIGrid(f"EPSG:{crs.to_epsg()}", Affine(p, 0.0, x0, 0.0, -p, y0), self.cells, self.cells)


# ------------------------------------------------------------------------------------------
# the world
# ------------------------------------------------------------------------------------------
def event_centre_xy(p: StereoSceneParams) -> tuple[float, float]:
    """The event region's centre in the AOI grid's map coordinates (m): the AOI centre + ``event_centre_m``."""
    g = p.grid()
    half = 0.5 * p.cells * p.posting_m
    return (g.transform.c + half + float(p.event_centre_m[0]), g.transform.f - half + float(p.event_centre_m[1]))


def make_buildings(p: StereoSceneParams) -> np.ndarray:
    """Every building of either epoch: rows (id, cx, cy, half_x, half_y, height, in_A, in_B), metres.

    One slot of the 32 m lattice holds at most one building; its size and place are drawn from the
    slot's own random stream, so a building does not depend on the AOI size. With an event region
    (``event_radius_m``), a building changes only when its centre lies in the region.
    """
    g = p.grid()
    x0, y0 = g.transform.c, g.transform.f
    side = p.cells * p.posting_m
    ex, ey = event_centre_xy(p)
    n = int(math.floor(side / SLOT_M))
    rows = []
    bid = 0
    for j in range(n):
        for i in range(n):
            rng = np.random.default_rng([p.seed, 31, i, j])
            u = rng.uniform(size=3)
            hx, hy = rng.uniform(4.0, 12.0, size=2)
            h = rng.uniform(4.0, 18.0)
            jx = rng.uniform(-1.0, 1.0) * (SLOT_M / 2 - hx - 2.0)
            jy = rng.uniform(-1.0, 1.0) * (SLOT_M / 2 - hy - 2.0)
            cx = x0 + (i + 0.5) * SLOT_M + jx
            cy = y0 - (j + 0.5) * SLOT_M + jy
            built = u[0] < p.built_fraction
            if p.event_radius_m is not None and math.hypot(cx - ex, cy - ey) > p.event_radius_m:
                in_a = in_b = built  # outside the event: nothing changes
            elif built:
                in_a, in_b = True, not (u[1] < p.demolished_fraction)
            else:
                in_a, in_b = False, bool(u[2] < p.new_fraction / max(1.0 - p.built_fraction, 1e-9) * p.built_fraction)
            if in_a or in_b:
                bid += 1
                rows.append((bid, cx, cy, hx, hy, h, float(in_a), float(in_b)))
    return np.asarray(rows, np.float64).reshape(-1, 8)


def _disc_fraction(g: AOIGrid, cx: float, cy: float, r: float) -> float:
    """Fraction of the AOI's area inside the disc (centre ``cx, cy``, radius ``r``, map metres), on a 512² lattice."""
    xa, ya, xb, yb = g.bounds
    u = (np.arange(512) + 0.5) / 512
    X, Y = np.meshgrid(xa + u * (xb - xa), ya + u * (yb - ya))
    return float(((X - cx) ** 2 + (Y - cy) ** 2 <= r * r).mean())


def _objects(buildings: np.ndarray, epoch: str, value: str = "height") -> np.ndarray:
    """Boxes of one epoch as :func:`~geocd.synth._kernels.dem_window` objects (kind 0)."""
    col = 6 if epoch == "A" else 7
    b = buildings[buildings[:, col] > 0.5]
    v = b[:, 5] if value == "height" else b[:, 0]
    return np.ascontiguousarray(np.column_stack([np.zeros(len(b)), b[:, 1], b[:, 2], b[:, 3], b[:, 4], v]))


def _near(objects: np.ndarray, xl: float, xr: float, yb: float, yt: float) -> np.ndarray:
    if objects.size == 0:
        return objects
    e = np.maximum(objects[:, 3], objects[:, 4]) + 1.0
    keep = (objects[:, 1] + e >= xl) & (objects[:, 1] - e <= xr) & (objects[:, 2] + e >= yb) & (objects[:, 2] - e <= yt)
    return np.ascontiguousarray(objects[keep])


def surface_window(
    p: StereoSceneParams,
    objects: np.ndarray,
    x0: float,
    y0: float,
    post: float,
    window: tuple[int, int, int, int],
    *,
    terrain: bool = True,
) -> np.ndarray:
    """float64 heights (terrain + ``objects``) on ``window`` (row0, col0, h, w) of the grid with corner
    (x0, y0) and square cells of ``post`` m. ``terrain=False``: the objects alone (e.g. ids)."""
    r0, c0, h, w = window
    out = np.empty((h, w), np.float64)
    sel = _near(objects, x0 + c0 * post, x0 + (c0 + w) * post, y0 - (r0 + h) * post, y0 - r0 * post)
    nil = np.zeros(0)
    K.dem_window(
        x0,
        y0,
        post,
        r0,
        c0,
        h,
        w,
        0.0,
        0.0,
        0.0,
        p.seed,
        SCALES_M if terrain else nil,
        AMPS_M if terrain else nil,
        30.0,
        0.0,
        0.0,
        sel,
        out,
    )
    if terrain:
        out += p.base_m
    return out


def height_band(p: StereoSceneParams) -> tuple[float, float]:
    """Heights (ellipsoidal, m) bracketing every surface of the scene."""
    return p.base_m - float(AMPS_M.sum()) - 2.0, p.base_m + float(AMPS_M.sum()) + 20.0


# ------------------------------------------------------------------------------------------
# views
# ------------------------------------------------------------------------------------------
def make_cameras(p: StereoSceneParams) -> dict[str, Any]:
    """Physical pushbroom cameras of every view (name → camera), covering the AOI over the height band."""
    from ..geodesy import to_lonlat
    from .sensors import make_pushbroom

    g = p.grid()
    lo, hi = height_band(p)
    xa, ya, xb, yb = g.bounds
    pts = []
    for x in (xa, 0.5 * (xa + xb), xb):
        for y in (ya, 0.5 * (ya + yb), yb):
            lon, lat = to_lonlat(x, y, g.crs)
            for z in (lo, hi):
                pts.append([float(lon), float(lat), z])
    cover = np.array(pts)
    lonc, latc = to_lonlat(0.5 * (xa + xb), 0.5 * (ya + yb), g.crs)
    cams = {}
    for ep, views in (("A", p.views_a), ("B", p.views_b)):
        for k, (along, across) in enumerate(views):
            name = f"{ep}_sat{k + 1}"
            cams[name] = make_pushbroom(
                float(lonc),
                float(latc),
                p.base_m,
                along_deg=along,
                across_deg=across,
                heading_deg=p.heading_deg,
                altitude_m=p.altitude_m,
                gsd_m=p.posting_m,
                cover_lonlath=cover,
                margin_px=8,
                name=name,
            )
    return cams


@dataclass(frozen=True)
class _View:
    name: str
    epoch: str
    camera: Any
    crs: Any
    gain: float
    dark: float
    haze: float
    index: int


LATTICE_PX = 16
HALO_PX = 4


def block_rays(view: _View, band: tuple[float, float], r0: int, c0: int, nr: int, nc: int):
    """Each pixel's ray of an image block as its map points at the top and the bottom of ``band``:
    (ax, ay, bx, by), each (nr, nc). Localized exactly on a 16-px lattice, bilinear in between."""
    from scipy.ndimage import map_coordinates

    from ..geodesy import from_lonlat

    L = LATTICE_PX
    rr = np.arange(r0, r0 + nr + L, L, dtype=float)
    cc = np.arange(c0, c0 + nc + L, L, dtype=float)
    R, C = np.meshgrid(rr + 0.5, cc + 0.5, indexing="ij")
    out = []
    for h in (band[1], band[0]):
        lon, lat = view.camera.localize(C.ravel(), R.ravel(), np.full(C.size, h))
        x, y = from_lonlat(lon, lat, view.crs)
        out += [np.asarray(x).reshape(R.shape), np.asarray(y).reshape(R.shape)]
    fr, fc = np.meshgrid(np.arange(nr) / L, np.arange(nc) / L, indexing="ij")
    return tuple(map_coordinates(a, [fr, fc], order=1, mode="nearest") for a in out)


def render_block(
    p: StereoSceneParams, view: _View, objects: np.ndarray, ids: np.ndarray, r0: int, c0: int, nr: int, nc: int
) -> tuple[np.ndarray, dict]:
    """uint16 counts (nr, nc) of an image block (rendered with a halo for the PSF, then cropped)."""
    from .render import SensorRadiometry, to_sensor_counts

    H = HALO_PX
    R0, C0, NR, NC = r0 - H, c0 - H, nr + 2 * H, nc + 2 * H
    band = height_band(p)
    ax, ay, bx, by = block_rays(view, band, R0, C0, NR, NC)
    ok = np.isfinite(ax) & np.isfinite(bx)
    g = p.grid()
    gx0, gy0 = g.transform.c, g.transform.f
    fs = 0.5 * p.posting_m  # DSM sampling of the renderer: half a cell
    xs = np.concatenate([ax[ok], bx[ok]])
    ys = np.concatenate([ay[ok], by[ok]])
    counts = np.zeros((nr, nc), np.uint16)
    if xs.size == 0:
        return counts, {"hit": 0.0}
    c_lo = int(math.floor((xs.min() - 2.0 - gx0) / fs))
    c_hi = int(math.ceil((xs.max() + 2.0 - gx0) / fs))
    r_lo = int(math.floor((gy0 - ys.max() - 2.0) / fs))
    r_hi = int(math.ceil((gy0 - ys.min() + 2.0) / fs))
    win = (r_lo, c_lo, r_hi - r_lo, c_hi - c_lo)
    dsm = surface_window(p, objects, gx0, gy0, fs, win)
    bid = surface_window(p, ids, gx0, gy0, fs, win, terrain=False)
    wx0 = gx0 + (c_lo + 0.5) * fs  # the window's first cell centre
    wy0 = gy0 - (r_lo + 0.5) * fs
    n = ax.size
    hx, hy, hz, sl = (np.empty(n) for _ in range(4))
    A = [np.ascontiguousarray(np.where(ok, a, 0.0).ravel()) for a in (ax, ay, bx, by)]
    K.march_dsm(
        *A,
        band[1],
        band[0],
        float(dsm.max()) + 0.5,
        float(dsm.min()) - 0.5,
        0.5 * fs,
        dsm,
        wx0,
        wy0,
        fs,
        hx,
        hy,
        hz,
        sl,
    )
    hz[~ok.ravel()] = np.nan
    # the building seen: the largest id among the 4 DSM samples around the hit (a wall hit lies on the
    # steep face between a roof sample and a ground sample)
    fc = np.clip((np.nan_to_num(hx) - wx0) / fs, 0, bid.shape[1] - 1.000001)
    fr = np.clip((wy0 - np.nan_to_num(hy)) / fs, 0, bid.shape[0] - 1.000001)
    ci, ri = fc.astype(np.int64), fr.astype(np.int64)
    b_at = np.rint(
        np.maximum(np.maximum(bid[ri, ci], bid[ri, ci + 1]), np.maximum(bid[ri + 1, ci], bid[ri + 1, ci + 1]))
    ).astype(np.int64)
    roofish = sl <= 3.0  # on a roof or the ground: the nearest sample decides
    b_near = np.rint(bid[np.rint(fr).astype(np.int64), np.rint(fc).astype(np.int64)]).astype(np.int64)
    b_at = np.where(roofish, b_near, b_at)
    alb = np.empty(n)
    K.big_albedo(hx, hy, hz, b_at, sl, int(p.seed), alb)
    rad = alb.reshape(NR, NC)
    radio = SensorRadiometry(
        nbits=11,
        gain=view.gain,
        dark=view.dark,
        haze=view.haze,
        psf_sigma_px=0.5,
        electrons_per_count=8.0,
        read_noise=2.0,
        bands="pan",
    )
    rng = np.random.default_rng([p.seed, 99, view.index, r0, c0])
    img = to_sensor_counts(np.broadcast_to(rad, (4, NR, NC)), radio, rng)[0]
    counts[:] = img[H : H + nr, H : H + nc]
    return counts, {"hit": float(np.isfinite(hz).mean())}


# ------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------
def _part(path: Path) -> Path:
    return path.with_name(f".{path.name}.part.tif")


def _write_view(
    p: StereoSceneParams,
    view: _View,
    rpc,
    path: Path,
    objects: np.ndarray,
    ids: np.ndarray,
    block: int,
    workers: int,
    prog,
    tags: dict,
) -> dict:
    import rasterio
    from rasterio.windows import Window

    cam = view.camera
    W, Hh = int(cam.width), int(cam.height)
    prof = {
        "driver": "GTiff",
        "width": W,
        "height": Hh,
        "count": 1,
        "dtype": "uint16",
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "nbits": 11,
        "rpcs": rpc.to_rasterio(),
        "BIGTIFF": "IF_SAFER",
    }
    tmp = _part(path)
    jobs = [(r, c, min(block, Hh - r), min(block, W - c)) for r in range(0, Hh, block) for c in range(0, W, block)]
    hits = []
    lock = threading.Lock()
    with rasterio.Env(GDAL_CACHEMAX=64), rasterio.open(tmp, "w", **prof) as ds:
        ds.update_tags(**tags)
        with ThreadPoolExecutor(max_workers=workers) as ex:
            pending = []
            done = 0
            it = iter(jobs)
            for _ in range(2 * workers):
                j = next(it, None)
                if j is not None:
                    pending.append((j, ex.submit(render_block, p, view, objects, ids, *j)))
            while pending:
                j, f = pending.pop(0)
                counts, info = f.result()
                with lock:
                    ds.write(counts[None], window=Window(j[1], j[0], j[3], j[2]))
                hits.append(info["hit"])
                done += 1
                prog(done / len(jobs), f"{view.name}: block {done}/{len(jobs)}")
                nj = next(it, None)
                if nj is not None:
                    pending.append((nj, ex.submit(render_block, p, view, objects, ids, *nj)))
    os.replace(tmp, path)
    return {"width": W, "height": Hh, "blocks": len(jobs), "hit_fraction": round(float(np.mean(hits)), 5)}


def _write_raster(
    path: Path, grid: AOIGrid, dtype: str, func, *, nodata=None, tags=None, strip: int = 1024, overview: bool = False
) -> Path:
    """A tiled GeoTIFF written strip by strip: ``func(row0, rows)`` gives each strip."""
    import rasterio
    from rasterio.windows import Window

    prof = {
        "driver": "GTiff",
        "width": grid.width,
        "height": grid.height,
        "count": 1,
        "dtype": dtype,
        "crs": grid.crs,
        "transform": grid.transform,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "compress": "deflate",
        "BIGTIFF": "IF_SAFER",
        **({"nodata": nodata} if nodata is not None else {}),
    }
    tmp = _part(path)
    with rasterio.open(tmp, "w", **prof) as ds:
        ds.update_tags(**(tags or {}))
        for r in range(0, grid.height, strip):
            h = min(strip, grid.height - r)
            ds.write(func(r, h).astype(dtype)[None], window=Window(0, r, grid.width, h))
    os.replace(tmp, path)
    return path


def make_stereo_scene(
    out_dir: os.PathLike | str,
    params: StereoSceneParams = StereoSceneParams(),
    *,
    block: int = 512,
    workers: int | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Write the scene (module docstring) into ``out_dir``; returns {"manifest", "truth", "report"}."""
    import geopandas as gpd
    import yaml
    from shapely.geometry import box

    from ..camera.rpc_fit import fit_rpc
    from ..io.atomic import write_text_atomic
    from ..io.vector import write_gpkg

    t_all = time.perf_counter()
    prog = ensure_progress(progress)
    p = params
    workers = workers or min(os.cpu_count() or 1, 4)
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(exist_ok=True)
    g = p.grid()
    gx0, gy0 = g.transform.c, g.transform.f
    bl = make_buildings(p)
    obj = {e: _objects(bl, e) for e in "AB"}
    ids = {e: _objects(bl, e, "id") for e in "AB"}
    tags = {"generator": "geocd.synth.bigstereo", "params": json.dumps(asdict(p))}
    ell = {"vertical_datum": "ellipsoid", "units": "metre"}
    rep: dict[str, Any] = {"params": asdict(p), "grid": g.to_dict(), "timings": {}}

    # --- truth on the AOI grid ------------------------------------------------------------------------
    t0 = time.perf_counter()
    T = out / "truth"
    for e in "AB":
        _write_raster(
            T / f"dsm_{e}.tif",
            g,
            "float32",
            lambda r, h, e=e: surface_window(p, obj[e], gx0, gy0, p.posting_m, (r, 0, h, g.width)),
            tags={**tags, **ell, "content": f"truth DSM epoch {e} at cell centres"},
        )

    def dh(r, h):
        return surface_window(p, obj["B"], gx0, gy0, p.posting_m, (r, 0, h, g.width)) - surface_window(
            p, obj["A"], gx0, gy0, p.posting_m, (r, 0, h, g.width)
        )

    _write_raster(T / "dh.tif", g, "float32", dh, tags={**tags, "units": "metre", "content": "DSM_B - DSM_A"})
    _write_raster(
        T / "change_mask.tif",
        g,
        "uint8",
        lambda r, h: np.abs(dh(r, h)) > p.change_threshold_m,
        tags={**tags, "content": f"1 where |DSM_B - DSM_A| > {p.change_threshold_m} m"},
    )
    f = 4  # the prior: bare terrain at 4 cells (2 m at 0.5 m)
    g2 = AOIGrid(g.crs, Affine(p.posting_m * f, 0.0, gx0, 0.0, -p.posting_m * f, gy0), g.width // f, g.height // f)
    none = np.zeros((0, 6))
    _write_raster(
        T / "dem_prior.tif",
        g2,
        "float32",
        lambda r, h: surface_window(p, none, gx0, gy0, p.posting_m * f, (r, 0, h, g2.width)),
        tags={**tags, **ell, "content": "bare terrain (no buildings) at 4 cells: the stereo search prior"},
    )
    status = np.where((bl[:, 6] > 0.5) & (bl[:, 7] > 0.5), "unchanged", np.where(bl[:, 6] > 0.5, "demolished", "new"))
    gdf = gpd.GeoDataFrame(
        {
            "building_id": bl[:, 0].astype(int),
            "height_m": bl[:, 5],
            "status": status,
            "in_A": bl[:, 6] > 0.5,
            "in_B": bl[:, 7] > 0.5,
        },
        geometry=[box(b[1] - b[3], b[2] - b[4], b[1] + b[3], b[2] + b[4]) for b in bl],
        crs=g.crs,
    )
    write_gpkg(T / "buildings.gpkg", {"buildings": gdf})
    rep["timings"]["truth_s"] = round(time.perf_counter() - t0, 2)
    rep["buildings"] = {s: int((status == s).sum()) for s in ("unchanged", "demolished", "new")}
    prog(0.05, "truth written")

    # --- views ----------------------------------------------------------------------------------------
    cams = make_cameras(p)
    lo, hi = height_band(p)
    rpc_h = (math.floor(lo - 10.0), math.ceil(hi + 15.0))
    views = []
    nv = len(cams)
    imgs: dict[str, list] = {"A": [], "B": []}
    for k, (name, cam) in enumerate(cams.items()):
        t0 = time.perf_counter()
        ep = name[0]
        rng = np.random.default_rng([p.seed, 7, k])
        v = _View(
            name,
            ep,
            cam,
            g.crs,
            gain=float(1500.0 * (1.0 if ep == "A" else 0.9) * rng.uniform(0.95, 1.05)),
            dark=float(rng.uniform(30, 50)),
            haze=float(0.02 + rng.uniform(0, 0.01)),
            index=k,
        )
        rpc, fit = fit_rpc(cam, rpc_h, source=f"geocd bigstereo: RPC00B fitted to the pushbroom model of {name}")
        path = out / "images" / f"{name}.tif"
        lo_p, hi_p = 0.05 + 0.95 * k / nv, 0.05 + 0.95 * (k + 1) / nv
        info = _write_view(
            p,
            v,
            rpc,
            path,
            obj[ep],
            ids[ep],
            block,
            workers,
            lambda fr, msg: prog(lo_p + (hi_p - lo_p) * fr, msg),
            {**tags, "epoch": ep, "GEOCD_SYNTH": f"bigstereo seed={p.seed}"},
        )
        views.append(
            {
                "name": name,
                "epoch": ep,
                **{k2: cam.info[k2] for k2 in ("along_deg", "across_deg", "off_nadir_deg")},
                "rpc_fit_check_max_px": fit.check_max_px,
                **info,
                "seconds": round(time.perf_counter() - t0, 1),
            }
        )
        (T / f"{name}.camera.json").write_text(json.dumps(cam.to_dict(), indent=1), encoding="utf-8")
        imgs[ep].append({"path": f"images/{name}.tif", "name": name})
    rep["views"] = views
    rep["rpc_height_range_m"] = list(rpc_h)

    # --- manifest -------------------------------------------------------------------------------------
    if p.event_radius_m is not None:
        ex, ey = event_centre_xy(p)
        rep["event"] = {
            "centre_xy": [ex, ey],
            "radius_m": float(p.event_radius_m),
            "area_fraction_of_aoi": round(_disc_fraction(g, ex, ey, float(p.event_radius_m)), 4),
        }
    b = g.bounds
    man = {
        "geocd_manifest": 1,
        "name": f"bigstereo_{p.cells}_s{p.seed}",
        "description": f"geocd.synth.bigstereo scene: {p.cells}² cells of {p.posting_m} m, two epochs, known "
        "demolished and new buildings (truth/)",
        "scene_class": "synthetic-blocks",
        "aoi": {"crs": f"EPSG:{g.crs.to_epsg()}", "bounds": [float(v) for v in b], "posting_m": p.posting_m},
        "dem": {"path": "truth/dem_prior.tif", "vertical_datum": "ellipsoid"},
        "orientation": False,
        "epochs": [{"name": "A", "images": imgs["A"]}, {"name": "B", "images": imgs["B"]}],
        "truth": {
            "dsm_A": "truth/dsm_A.tif",
            "dsm_B": "truth/dsm_B.tif",
            "dh": "truth/dh.tif",
            "change_mask": "truth/change_mask.tif",
            "buildings": "truth/buildings.gpkg",
        },
    }
    manifest = write_text_atomic(out / "scene.yaml", yaml.safe_dump(man, sort_keys=False))
    rep["timings"]["total_s"] = round(time.perf_counter() - t_all, 2)
    truth = write_text_atomic(T / "truth.json", json.dumps(rep, indent=1, default=str))
    prog(1.0, "done")
    return {"manifest": Path(manifest), "truth": Path(truth), "report": rep}
