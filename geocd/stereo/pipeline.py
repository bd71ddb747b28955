"""Stereo on a scene manifest: every pair of every epoch → pair-DEM GeoTIFFs.

This is the only part of :mod:`geocd.stereo` that touches files (with
:mod:`geocd.stereo.products`): it reads image windows for the AOI grid, the
prior DEM and the cameras, and writes ``<out>/stereo/<epoch>/<a>__<b>.tif``.
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

from ..camera import Camera
from ..errors import ConfigError, NoOverlapError
from ..geodesy import AOIGrid, as_crs, from_lonlat, utm_crs_for
from ..progress import Progress, ensure_progress, sub_progress
from .match import height_bounds, match_pair
from .params import StereoParams
from .products import FLAGS, FLAGS_NOT_EXAMINED, PairDEM, write_pair_dem
from .sweep import ImageChip, image_sampling_px_per_m, prepare_chip


#: completeness (valid share of the AOI cells a pair's two images both see) below which a pair-DEM is reported
#: as incomplete: the issue's figure ("a low completeness (< 70 % of the AOI) is a warning")
LOW_COMPLETENESS = 0.70

#: share of the AOI outside a pair's common footprint above which the AOI is reported as mostly unseen by the pair
AOI_UNSEEN_SHARE = 0.5


class StereoCompletenessWarning(UserWarning):
    """A pair-DEM holds heights on too small a share of the AOI (see :func:`pair_dem_warnings`)."""


class StereoPairNote(UserWarning):
    """What the stereo step decided on its own (a pair left out); the CLI prints it as a note, not a warning."""

    is_note = True


@dataclass(frozen=True)
class EpochImage:
    """An image of an epoch with its camera."""

    name: str
    path: Path
    camera: Camera


def load_epoch_images(manifest, epoch) -> list[EpochImage]:
    """The images of an epoch with their cameras (any kind), in manifest order."""
    from ..io.cameras import load_camera

    out = []
    for spec in epoch.images:
        cam = load_camera(spec.path, spec.camera)
        out.append(EpochImage(spec.name or spec.path.stem, Path(spec.path), cam))
    return out


def _sensor_kind(camera: Camera) -> str:
    """The kind of sensor geometry (a corrected camera reports the camera underneath)."""
    return getattr(camera, "sensor_kind", camera.kind)


def pair_path(out_dir: os.PathLike | str, epoch: str, a: str, b: str) -> Path:
    """Where the pair-DEM of images ``a`` and ``b`` of ``epoch`` goes."""
    return Path(out_dir) / "stereo" / epoch / f"{a}__{b}.tif"


# ---------------------------------------------------------------------------------------------
# image windows
# ---------------------------------------------------------------------------------------------
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
    c = np.concatenate(cols)
    r = np.concatenate(rows)
    ok = np.isfinite(c) & np.isfinite(r)
    if not ok.any():
        return None
    c0 = max(int(math.floor(c[ok].min())) - margin_px, 0)
    r0 = max(int(math.floor(r[ok].min())) - margin_px, 0)
    c1 = min(int(math.ceil(c[ok].max())) + margin_px, width)
    r1 = min(int(math.ceil(r[ok].max())) + margin_px, height)
    if c1 - c0 < 2 or r1 - r0 < 2:
        return None
    return c0, r0, c1, r1


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
    from rasterio.windows import Window

    from ..io.raster import _open, read_image

    with _open(path) as ds:
        W, H = ds.width, ds.height
    box = image_window_for_grid(camera, grid, lo_m, hi_m, margin_px, W, H)
    if box is None:
        raise NoOverlapError(
            f"image {path} does not see the AOI {grid.bounds} ({grid.crs.name}) at heights "
            f"{lo_m:.0f}..{hi_m:.0f} m; check the AOI, the image's camera and the height range"
        )
    c0, r0, c1, r1 = box
    img = read_image(path, window=Window(c0, r0, c1 - c0, r1 - r0))
    return prepare_chip(img.data, img.valid, col0=c0, row0=r0, name=name or Path(path).stem, block_px=block_px)


# ---------------------------------------------------------------------------------------------
# AOI
# ---------------------------------------------------------------------------------------------
def _footprint_xy(camera: Camera, h: float, crs) -> Any:
    from shapely.geometry import Polygon

    fp = camera.footprint(h)
    lon, lat = np.asarray(fp.exterior.coords).T
    x, y = from_lonlat(lon, lat, crs)
    return Polygon(np.column_stack([x, y]))


#: bytes per AOI-grid cell: a pair-DEM held in memory (z, score, g, ncc, ssd, raw z, window score: float32;
#: valid, flags: 1 byte), the transient of writing one (stacked bands, the COG's in-memory copy and overviews),
#: and one pair-DEM file uncompressed (7 float32 bands + 1/3 overviews)
PAIR_MEMORY_PER_CELL = 30
WORK_MEMORY_PER_CELL = 150
PAIR_FILE_PER_CELL = 37


def check_stereo_resources(
    grid: AOIGrid, n_pairs: int, out: os.PathLike | str | None, *, keep_arrays: bool = False
) -> None:
    """Refuse stereo on a grid that cannot fit in memory or on disk, before any matching (see
    :func:`geocd.io.outputs.check_resources`)."""
    from ..io.outputs import available_memory_bytes, check_resources

    cells = int(grid.width) * int(grid.height)
    mem = cells * (PAIR_MEMORY_PER_CELL * (n_pairs if keep_arrays else 1) + WORK_MEMORY_PER_CELL)
    avail = available_memory_bytes()
    fit = ""
    if avail and mem > avail:
        fit = f" (about --posting {grid.posting_m * math.sqrt(mem / avail) * 1.1:.2g} would fit)"
    check_resources(
        f"stereo on a {grid.width} x {grid.height} grid at {grid.posting_m:g} m ({n_pairs} pair(s))",
        memory_bytes=mem,
        disk_bytes=cells * PAIR_FILE_PER_CELL * n_pairs,
        largest_file_bytes=cells * PAIR_FILE_PER_CELL,
        out=out,
        fix=f"match tile by tile with bounded memory (`geocd stereo --tiled`), or use a coarser "
        f"posting{fit}, a smaller AOI (aoi.bounds), or fewer images",
    )


def early_resource_check(m, grid: AOIGrid | None, posting_m: float | None, out) -> None:
    """Before any step (orientation included): a grid given or fixed by the manifest's AOI that cannot hold even
    one pair-DEM is refused at once (the exact check, with the pair count, follows once the pairs are known)."""
    if grid is None and m.aoi is not None and m.aoi.bounds is not None and m.aoi.crs:
        p = posting_m or m.aoi.posting_m
        if p:
            grid = AOIGrid.from_bounds(*m.aoi.bounds, float(p), as_crs(m.aoi.crs))
    if grid is not None:
        check_stereo_resources(grid, 1, out)


def _check_aoi_sees_images(bounds, crs, images: Sequence[EpochImage], dem_median: float | None) -> None:
    """An AOI that no image sees is the AOI's fault: say how far it is from the images (before any DEM is read)."""
    from shapely.geometry import box
    from shapely.ops import unary_union

    fps = []
    for im in images:
        r = im.camera.height_range() or (0.0, 0.0)
        h = dem_median if dem_median is not None and np.isfinite(dem_median) else 0.5 * (r[0] + r[1])
        try:
            fps.append(_footprint_xy(im.camera, h, crs))
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


def _ground_height_hint(images: Sequence[EpochImage], crs, dem_median: float | None, params: StereoParams) -> float:
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
        inter = _footprint_xy(a.camera, mid, crs).intersection(_footprint_xy(b.camera, mid, crs))
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


def _pairs_seeing_the_aoi(pairs: list, grid: AOIGrid, dem, params: StereoParams) -> tuple[list, list[str]]:
    """The pairs whose two images see some of the AOI together, and a note per pair left out.

    Raises
    ------
    NoOverlapError
        No pair is left.
    """
    kept, notes = [], []
    for e, a, b in pairs:
        lo, hi, _ = height_bounds(grid, [a.camera, b.camera], dem, params)
        lo, hi = float(np.nanmin(lo)), float(np.nanmax(hi))
        if pair_overlaps_aoi(a.camera, b.camera, grid, (lo, 0.5 * (lo + hi), hi)):
            kept.append((e, a, b))
            continue
        note = (
            f"pair {e.name}/{a.name}__{b.name} skipped: the two images see none of the AOI together "
            f"(footprints at {lo:.0f}..{hi:.0f} m)"
        )
        notes.append(note)
        warnings.warn(note, StereoPairNote, stacklevel=3)
    if not kept:
        raise NoOverlapError(
            f"no image pair sees any of the AOI {tuple(round(float(v), 1) for v in grid.bounds)} "
            f"({grid.crs.to_string()}) together ({len(pairs)} pair(s) tried), so there is nothing to match; check "
            "the cameras (positions, orientation, --height-range) and the AOI (aoi.bounds), or add images that overlap"
        )
    return kept, notes


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
    from shapely.ops import unary_union

    all_images = [im for ims in images_by_epoch.values() for im in ims]
    if not all_images:
        raise ConfigError("the manifest has no images to match; list images under epochs[].images")
    spec = manifest.aoi
    crs = as_crs(spec.crs) if spec is not None and spec.crs else None
    if spec is not None and spec.vector is not None and spec.bounds is None:
        from ..io.vector import read_footprints

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
    h = _ground_height_hint(all_images, crs, dem_median, params)
    if bounds is None:
        fps = {im.name: _footprint_xy(im.camera, h, crs) for im in all_images}
        all_frames = all(_sensor_kind(im.camera) == "frame" for im in all_images)
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


def pair_overlaps_aoi(a: Camera, b: Camera, grid: AOIGrid, heights: Sequence[float]) -> bool:
    """Whether the two cameras' ground footprints share some of the AOI at one of ``heights`` at least.

    A camera without a footprint (its corners do not reach the ground) counts as overlapping: the matcher decides.
    """
    from shapely.geometry import box

    aoi = box(*grid.bounds)
    for h in heights:
        try:
            o = _footprint_xy(a, float(h), grid.crs).intersection(_footprint_xy(b, float(h), grid.crs))
        except Exception:  # noqa: BLE001 - no footprint at this height: leave it to the matcher
            return True
        if o.intersects(aoi) and o.intersection(aoi).area > 0:
            return True
    return False


def pair_dem_warnings(
    key: str, pd: PairDEM, *, min_completeness: float = LOW_COMPLETENESS, aoi_unseen: bool = True
) -> list[str]:
    """What a user must hear about a pair-DEM: a low completeness, an AOI mostly outside the pair's view.

    Completeness here is the valid share of the AOI cells both images see (cells not flagged ``out_of_image``;
    cells a tiered run did not examine are left out); below ``min_completeness`` (70 %, :data:`LOW_COMPLETENESS`)
    the warning names the main reasons from the flags band (cells per flag). An AOI more than half outside the
    pair's common footprint (:data:`AOI_UNSEEN_SHARE`) is a warning of its own (``aoi_unseen``; off when the AOI
    is by construction the union of several pairs' overlaps).
    """
    valid = np.asarray(pd.valid, bool)
    flags = np.asarray(pd.flags) if pd.flags is not None else np.zeros(valid.shape, np.uint8)
    examined = flags != FLAGS_NOT_EXAMINED
    seen = examined & ((flags & FLAGS["out_of_image"]) == 0)
    n_exam, n_seen = int(examined.sum()), int(seen.sum())
    out = []
    if aoi_unseen and n_exam and (n_exam - n_seen) / n_exam > AOI_UNSEEN_SHARE:
        out.append(
            f"pair-DEM {key}: {(n_exam - n_seen) / n_exam:.0%} of the AOI is outside what both images see "
            "(flag out_of_image), so the pair-DEM covers only a part of it; give an AOI inside the images' overlap "
            "(aoi.bounds) or leave the AOI out to use the overlap"
        )
    if n_seen:
        comp = float((valid & seen).sum()) / n_seen
        if comp < min_completeness:
            bad = seen & ~valid
            counts = [
                (name, int((bad & ((flags & bit) != 0)).sum()))
                for name, bit in FLAGS.items()
                if name not in ("out_of_image", "filled")
            ]
            counts = sorted((c for c in counts if c[1]), key=lambda c: -c[1])[:3]
            reasons = ", ".join(f"{n} {c} cells ({c / n_seen:.0%})" for n, c in counts) or "none flagged"
            out.append(
                f"pair-DEM {key}: completeness {comp:.0%} of the {n_seen} AOI cells both images see, below "
                f"{min_completeness:.0%} (the share under which geocd calls a pair-DEM incomplete); main reasons "
                f"(flags band): {reasons}. Heights are missing there and no change can be tested there: check the "
                "height range (--height-range or the DEM), the images' overlap, dates and lighting, or add a view"
            )
    return out


# ---------------------------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------------------------
def run_stereo(
    manifest,
    *,
    epochs: Sequence[str] | None = None,
    out_dir: os.PathLike | str | None = None,
    params: StereoParams = StereoParams(),
    grid: AOIGrid | None = None,
    posting_m: float | None = None,
    overwrite: bool = True,
    progress: Progress | None = None,
    keep_arrays: bool = False,
    pairs: str = "all",
    orient: bool = True,
) -> dict[str, Any]:
    """Match every pair of images of the selected epochs and write their pair-DEMs.

    Parameters
    ----------
    manifest : geocd.io.manifest.Manifest or a path to one
    epochs : names of the epochs to process (default: all with ≥ 2 images)
    out_dir : output folder (default: the manifest's ``output``)
    grid : AOI grid (default: :func:`default_aoi_grid`)
    keep_arrays : also return the :class:`PairDEM` objects
    pairs : "all" (every pair of an epoch) or "same-kind" (only pairs of images whose cameras are of
        the same kind, e.g. satellite–satellite and aerial–aerial: mixed pairs differ in GSD and
        spectral band and match poorly)
    orient : apply the manifest's cross-image orientation first (:func:`geocd.orientation.orient_manifest`;
        by default on when the manifest has two epochs); False when the caller already did

    Returns
    -------
    dict with ``outputs`` ({"<epoch>/<a>__<b>": path}), ``grid``, ``warnings`` (the pair-DEMs' completeness
    warnings, :func:`pair_dem_warnings`), ``notes`` (pairs left out because they see none of the AOI together)
    and, with ``keep_arrays``, ``pairs`` ({key: PairDEM}).

    Raises
    ------
    ConfigError
        A selected epoch has fewer than two images.
    NoOverlapError
        No pair of images sees any of the AOI together (before any matching).
    """
    from ..io.atomic import protect_inputs
    from ..io.manifest import Manifest, load_manifest
    from ..io.raster import read_dem

    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    prog = ensure_progress(progress)
    selected = [m.epoch(e) for e in epochs] if epochs else [e for e in m.epochs if len(e.images) >= 2]
    if not selected:
        raise ConfigError(
            "no epoch of the manifest has two images or more, so there is no stereo pair to match; "
            "add images or name an epoch with --epoch"
        )
    for e in selected:
        if len(e.images) < 2:
            raise ConfigError(f"epoch {e.name!r} has {len(e.images)} image(s); stereo needs at least two")
    out = Path(out_dir) if out_dir is not None else m.output_dir()
    early_resource_check(m, grid, posting_m, out)
    if orient:
        from ..orientation import orient_manifest

        m, _ = orient_manifest(m, out_dir=out, grid=grid, stereo_params=params)
        selected = [m.epoch(e.name) for e in selected]
    images = {e.name: load_epoch_images(m, e) for e in selected}
    protect_inputs(*[im.path for ims in images.values() for im in ims])
    dem_median = None
    if grid is None and m.dem is not None:
        d0 = read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum).to_ellipsoidal()
        dem_median = float(np.nanmedian(d0.height_m))
    aoi_info: dict = {}
    if grid is None:
        grid = default_aoi_grid(m, images, posting_m=posting_m, dem_median=dem_median, params=params, info=aoi_info)
    if pairs not in ("all", "same-kind"):
        raise ConfigError(f"pairs must be 'all' or 'same-kind', got {pairs!r}")
    pairs = [
        (e, a, b)
        for e in selected
        for a, b in itertools.combinations(images[e.name], 2)
        if pairs == "all" or _sensor_kind(a.camera) == _sensor_kind(b.camera)
    ]
    if not pairs:
        raise ConfigError(
            "no image pair left to match (with pairs='same-kind', each epoch needs two images whose "
            "cameras are of the same kind); use pairs='all'"
        )
    dem = None
    if m.dem is not None:
        dem = read_dem(m.dem.path, grid=grid, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m
    pairs, notes = _pairs_seeing_the_aoi(pairs, grid, dem, params)
    check_stereo_resources(grid, len(pairs), out, keep_arrays=keep_arrays)
    quality: list[str] = []
    outputs: dict[str, Path] = {}
    kept: dict[str, PairDEM] = {}
    chips: dict[tuple[str, str], ImageChip] = {}
    # each image is read once, over the heights of every pair it belongs to
    span: dict[tuple[str, str], tuple[float, float]] = {}
    for e, a, b in pairs:
        lo, hi, _ = height_bounds(grid, [a.camera, b.camera], dem, params)
        for im in (a, b):
            k = (e.name, im.name)
            old = span.get(k, (np.inf, -np.inf))
            span[k] = (min(old[0], float(np.min(lo))), max(old[1], float(np.max(hi))))
    for i, (e, a, b) in enumerate(pairs):
        key = f"{e.name}/{a.name}__{b.name}"
        for k in [k for k in chips if k[0] != e.name]:  # one epoch's images in memory at a time
            del chips[k]
        p = sub_progress(prog, i / len(pairs), (i + 1) / len(pairs), prefix=f"pair {i + 1}/{len(pairs)} ")
        for im in (a, b):
            if (e.name, im.name) not in chips:
                chips[(e.name, im.name)] = read_chip(
                    im.path,
                    im.camera,
                    grid,
                    *span[(e.name, im.name)],
                    name=im.name,
                    margin_px=16 + 2 * params.window,
                    block_px=params.norm_block_px,
                )
        pd = match_pair(
            chips[(e.name, a.name)],
            chips[(e.name, b.name)],
            a.camera,
            b.camera,
            grid,
            dem=dem,
            params=params,
            epoch=e.name,
            progress=p,
        )
        path = write_pair_dem(
            pair_path(out, e.name, a.name, b.name),
            pd,
            overwrite=overwrite,
            tags={"images": [str(a.path), str(b.path)], "manifest": str(m.path or "")},
        )
        outputs[key] = path
        for w in pair_dem_warnings(key, pd, aoi_unseen=not aoi_info.get("union", False)):
            quality.append(w)
            warnings.warn(w, StereoCompletenessWarning, stacklevel=2)
        if keep_arrays:
            kept[key] = pd
    prog(1.0, "stereo done")
    res: dict[str, Any] = {"outputs": outputs, "grid": grid, "warnings": quality, "notes": notes}
    if keep_arrays:
        res["pairs"] = kept
    return res
