"""A manifest's images on the ground: the epochs' images with their cameras, the AOI grid, image windows.

What every method that works on a manifest's images starts from (stereo, orientation, ortho, the change screen,
probchange, mpp): :func:`load_epoch_images`, :func:`default_aoi_grid` (the manifest's AOI, else what the images see
together, at their ground sampling distance), :func:`read_chip` (the window of an image that the AOI sees,
normalized for matching) and the footprints and height hint behind them. Nothing here runs a method over the
scene; the height hint alone makes one coarse match of the first pair when no DEM gives the ground's height.
"""

from __future__ import annotations

import itertools
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from rasterio.windows import Window
from shapely.geometry import Polygon, box
from shapely.ops import unary_union

from ..camera import Camera
from ..errors import ConfigError, NoOverlapError
from ..geodesy import AOIGrid, as_crs, from_lonlat, utm_crs_for
from ..io.cameras import load_camera
from ..io.raster import _open, read_image
from ..io.vector import read_footprints
from .match import match_pair
from .params import StereoParams
from .products import FLAGS, PairDEM
from .sweep import ImageChip, image_sampling_px_per_m, prepare_chip


@dataclass(frozen=True)
class EpochImage:
    """An image of an epoch with its camera."""

    name: str
    path: Path
    camera: Camera


def load_epoch_images(manifest, epoch) -> list[EpochImage]:
    """The images of an epoch with their cameras (any kind), in manifest order."""
    out = []
    for spec in epoch.images:
        cam = load_camera(spec.path, spec.camera)
        out.append(EpochImage(spec.name or spec.path.stem, Path(spec.path), cam))
    return out


def sensor_kind(camera: Camera) -> str:
    """The kind of sensor geometry (a corrected camera reports the camera underneath)."""
    return getattr(camera, "sensor_kind", camera.kind)


def grid_outline_xy(grid: AOIGrid, n: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Points along the grid's border and a coarse interior lattice (map coordinates)."""
    l, b, r, t = grid.bounds
    u = np.linspace(0.0, 1.0, n)
    X, Y = np.meshgrid(l + (r - l) * u, b + (t - b) * u)
    return X.ravel(), Y.ravel()


def image_window_for_grid(
    camera: Camera, grid: AOIGrid, lo_m: float, hi_m: float, margin_px: int, width: int, height: int
) -> tuple[int, int, int, int] | None:
    """(col0, row0, col1, row1) of the image pixels the grid can project to; None when outside."""
    x, y = grid_outline_xy(grid)
    pr = camera.ground_projector(x, y, grid.crs)
    cols, rows = [], []
    for h in (lo_m, 0.5 * (lo_m + hi_m), hi_m):
        c, r = pr.project(np.full(x.shape, h))
        cols.append(c)
        rows.append(r)
    return box_from_points(np.concatenate(cols), np.concatenate(rows), margin_px, width, height)


def box_from_points(
    col: np.ndarray, row: np.ndarray, margin_px: int, width: int, height: int
) -> tuple[int, int, int, int] | None:
    """(col0, row0, col1, row1): the pixel box of the finite image points, grown by ``margin_px`` and clipped to a
    ``width`` × ``height`` image; None when no point is finite or the box is under 2 pixels on a side."""
    ok = np.isfinite(col) & np.isfinite(row)
    if not ok.any():
        return None
    c0 = max(int(math.floor(col[ok].min())) - margin_px, 0)
    r0 = max(int(math.floor(row[ok].min())) - margin_px, 0)
    c1 = min(int(math.ceil(col[ok].max())) + margin_px, width)
    r1 = min(int(math.ceil(row[ok].max())) + margin_px, height)
    if c1 - c0 < 2 or r1 - r0 < 2:
        return None
    return c0, r0, c1, r1


def read_grid_window(
    path: os.PathLike | str,
    camera: Camera,
    grid: AOIGrid,
    lo_m: float,
    hi_m: float,
    width: int,
    height: int,
    *,
    margin_px: int,
    check: str,
):
    """Read the window of a ``width`` × ``height`` image that the grid sees between two heights.

    Returns
    -------
    (RasterImage of the window, col0, row0)

    Raises
    ------
    NoOverlapError
        The image does not see the AOI at any height in [lo_m, hi_m]; the message ends with ``check``, what to
        check besides the AOI and the camera.
    """
    box = image_window_for_grid(camera, grid, lo_m, hi_m, margin_px, width, height)
    if box is None:
        raise NoOverlapError(
            f"image {path} does not see the AOI {grid.bounds} ({grid.crs.name}) at heights "
            f"{lo_m:.0f}..{hi_m:.0f} m; check the AOI, the image's camera and {check}"
        )
    c0, r0, c1, r1 = box
    return read_image(path, window=Window(c0, r0, c1 - c0, r1 - r0)), c0, r0


def read_chip(
    path: os.PathLike | str,
    camera: Camera,
    grid: AOIGrid,
    lo_m: float,
    hi_m: float,
    *,
    name: str = "",
    margin_px: int = 16,
    block_px: int = 256,
) -> ImageChip:
    """Read and normalize the window of an image that the AOI grid sees between two heights.

    Raises
    ------
    NoOverlapError
        The image does not see the AOI at any height in [lo_m, hi_m].
    EmptyDataError
        The window is entirely nodata.
    """
    with _open(path) as ds:
        W, H = ds.width, ds.height
    img, c0, r0 = read_grid_window(path, camera, grid, lo_m, hi_m, W, H, margin_px=margin_px, check="the height range")
    return prepare_chip(img.data, img.valid, col0=c0, row0=r0, name=name or Path(path).stem, block_px=block_px)


def footprint_xy(camera: Camera, h: float, crs) -> Any:
    fp = camera.footprint(h)
    lon, lat = np.asarray(fp.exterior.coords).T
    x, y = from_lonlat(lon, lat, crs)
    return Polygon(np.column_stack([x, y]))


def _check_aoi_sees_images(bounds, crs, images: Sequence[EpochImage], dem_median: float | None) -> None:
    """An AOI that no image sees is the AOI's fault: say how far it is from the images (before any DEM is read)."""
    fps = []
    for im in images:
        r = im.camera.height_range() or (0.0, 0.0)
        h = dem_median if dem_median is not None and np.isfinite(dem_median) else 0.5 * (r[0] + r[1])
        try:
            fps.append(footprint_xy(im.camera, h, crs))
        except Exception:  # noqa: BLE001 - a camera without a footprint: nothing to check against
            return
    seen = unary_union(fps)
    aoi = box(*bounds)
    if not seen.is_empty and not aoi.intersects(seen):
        d = aoi.distance(seen)
        raise NoOverlapError(
            f"the AOI {tuple(round(float(v), 1) for v in bounds)} (aoi.bounds in {crs.to_string()}) is "
            f"{d / 1000:.1f} km from what the images see {tuple(round(float(v), 1) for v in seen.bounds)}; fix the "
            "manifest's aoi.bounds / aoi.crs (or leave the AOI out to use the images' overlap)"
        )


def ground_height_hint(images: Sequence[EpochImage], crs, dem_median: float | None, params: StereoParams) -> float:
    """A typical ground height of the scene: the prior DEM's median, else a coarse match of the first pair."""
    if dem_median is not None and np.isfinite(dem_median):
        return float(dem_median)
    ranges = [im.camera.height_range() for im in images]
    ranges = [r for r in ranges if r is not None]
    if params.height_range_m is not None:
        lo, hi = params.height_range_m
    elif ranges:
        lo, hi = max(r[0] for r in ranges), min(r[1] for r in ranges)
    else:
        raise ConfigError(
            "no height range to place the AOI: the cameras give none and no DEM was given; add "
            "'dem:' or 'aoi:' to the manifest, or pass --height-range MIN MAX"
        )
    mid = 0.5 * (lo + hi)
    if len(images) < 2:
        return mid
    a, b = images[0], images[1]
    try:
        inter = footprint_xy(a.camera, mid, crs).intersection(footprint_xy(b.camera, mid, crs))
        if inter.is_empty:
            return mid
        l, bt, r, t = inter.bounds
        posting = max((r - l), (t - bt)) / 48.0
        grid = AOIGrid.from_bounds(l, bt, r, t, posting, crs)
        p = params.replace(height_range_m=(lo, hi), window=5, occlusion_check=False, min_base_height=0.0)
        ca = read_chip(a.path, a.camera, grid, lo, hi, name=a.name, block_px=params.norm_block_px)
        cb = read_chip(b.path, b.camera, grid, lo, hi, name=b.name, block_px=params.norm_block_px)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pd = match_pair(ca, cb, a.camera, b.camera, grid, params=p)
        return _hint_from_match(pd, lo, hi, mid)
    except Exception:  # a hint only: fall back on the middle of the range
        return mid


def _hint_from_match(pd: PairDEM, lo: float, hi: float, fallback: float) -> float:
    """The median matched height of a coarse match over the cameras' whole height range.

    Such a range (an RPC's −20…2610 m) necessarily takes most cells out of an image at some of its heights,
    so the matcher flags them ``range_limit`` (their search was incomplete); for a hint that is no reason to
    drop a match that is otherwise sound. Heights within two steps of the range's ends stay out (a minimum
    at the edge is no minimum).
    """
    if pd.flags is None or pd.z_raw_m is None:
        z = pd.z_m[pd.valid]
    else:
        edge = 2.0 * float(pd.meta.get("step_m", 0.0) or 0.0) * 2 ** max(int(pd.meta.get("levels", 1)) - 1, 0)
        z = pd.z_raw_m[((pd.flags & ~np.uint8(FLAGS["range_limit"])) == 0) & np.isfinite(pd.z_raw_m)]
        z = z[(z > lo + edge) & (z < hi - edge)]
    return float(np.median(z)) if z.size >= 10 else fallback


def default_aoi_grid(
    manifest,
    images_by_epoch: dict[str, list[EpochImage]],
    *,
    posting_m: float | None = None,
    dem_median: float | None = None,
    params: StereoParams = StereoParams(),
    info: dict | None = None,
) -> AOIGrid:
    """The AOI grid of a manifest: its ``aoi`` when given, else what every image sees.

    Default extent: the intersection of all images' ground footprints (at the
    scene's typical height), so every pair-DEM of every epoch lives on one grid;
    when that is empty, the union of the pairwise overlaps within epochs.
    Frame cameras (drone or aerial strips, where the first and the last frames need not overlap): the union of
    the areas at least two views of an epoch see. Default CRS: the UTM zone of the centre; default posting: the
    images' median ground sampling distance (rounded to 5 cm), sampled where their projection is finite.
    ``info``, when given, gets ``union`` (True when the AOI is a union of pairwise overlaps).

    Raises
    ------
    NoOverlapError
        No two images of an epoch overlap on the ground (no AOI given).
    """
    all_images = [im for ims in images_by_epoch.values() for im in ims]
    if not all_images:
        raise ConfigError("the manifest has no images to match; list images under epochs[].images")
    spec = manifest.aoi
    crs = as_crs(spec.crs) if spec is not None and spec.crs else None
    if spec is not None and spec.vector is not None and spec.bounds is None:
        gdf = read_footprints(spec.vector, crs=crs)
        crs = crs or as_crs(gdf.crs)
        bounds = tuple(gdf.total_bounds)
    else:
        bounds = spec.bounds if spec is not None else None
    if crs is None or bounds is None:
        r0 = all_images[0].camera.height_range() or (0.0, 0.0)
        fp = all_images[0].camera.footprint(0.5 * (r0[0] + r0[1]) if dem_median is None else dem_median)
        c = fp.centroid
        crs = crs or utm_crs_for(c.x, c.y)
    if bounds is not None:
        _check_aoi_sees_images(bounds, crs, all_images, dem_median)
    h = ground_height_hint(all_images, crs, dem_median, params)
    if bounds is None:
        fps = {im.name: footprint_xy(im.camera, h, crs) for im in all_images}
        all_frames = all(sensor_kind(im.camera) == "frame" for im in all_images)
        inter = None
        for f in fps.values():
            inter = f if inter is None else inter.intersection(f)
        if all_frames or inter is None or inter.is_empty or inter.area <= 0:
            parts = []
            for ims in images_by_epoch.values():
                for a, b in itertools.combinations(ims, 2):
                    o = fps[a.name].intersection(fps[b.name])
                    if not o.is_empty and o.area > 0:
                        parts.append(o)
            if not parts:
                raise NoOverlapError(
                    f"no two images of an epoch overlap on the ground (footprints at {h:.0f} m: "
                    + ", ".join(f"{k} {tuple(round(float(v)) for v in f.bounds)}" for k, f in fps.items())
                    + f" in {crs.to_string()}), so there is no stereo pair to match; check the cameras (positions, "
                    "orientation, the height range: --height-range) or give the AOI the images see (aoi.bounds)"
                )
            inter = unary_union(parts)
            if info is not None:
                info["union"] = True
            if not all_frames:
                warnings.warn(
                    "the images have no area in common; the AOI is the union of the pairwise overlaps, so "
                    "pair-DEMs cover different parts of it",
                    stacklevel=2,
                )
        bounds = inter.bounds
    if posting_m is None and spec is not None and spec.posting_m:
        posting_m = spec.posting_m
    if posting_m is None:
        posting_m = _default_posting(all_images, bounds, crs, h)
    l, b, r, t = bounds
    return AOIGrid.from_bounds(l, b, r, t, float(posting_m), crs)


def _default_posting(images: Sequence[EpochImage], bounds, crs, h: float) -> float:
    """The images' median ground sampling distance over the AOI, rounded to 5 cm.

    Sampled on a 9 × 9 lattice of the AOI, each image only where its projection is finite and inside the image
    (a frame camera projects ground far outside its view to NaN or to points off its sensor).
    """
    l, b, r, t = bounds
    probe = AOIGrid.from_bounds(l, b, r, t, max((r - l), (t - b)) / 8.0, crs)
    rows, cols = (a.ravel() for a in np.meshgrid(np.arange(probe.height), np.arange(probe.width), indexing="ij"))
    x, y = probe.xy(rows, cols)
    gsd = []
    for im in images:
        with np.errstate(all="ignore"):
            s = image_sampling_px_per_m(im.camera, probe, rows, cols, h)
            c, rr = im.camera.ground_projector(x, y, crs).project(np.full(x.shape, h))
        ok = np.isfinite(s) & (s > 0) & im.camera.in_image(c, rr)
        if ok.any():
            gsd.append(float(np.median(1.0 / s[ok])))
    if not gsd:
        raise NoOverlapError(
            f"no image sees the AOI {tuple(round(float(v), 1) for v in bounds)} ({crs.to_string()}) at {h:.0f} m, "
            "so its ground sampling distance is unknown; check the cameras and the height range (--height-range), "
            "or give the AOI and its posting (aoi.bounds, --posting)"
        )
    return max(0.05, round(float(np.median(gsd)) / 0.05) * 0.05)
