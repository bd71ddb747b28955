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
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..camera import Camera
from ..errors import ConfigError, NoOverlapError
from ..geodesy import AOIGrid, as_crs
from ..orientation import orient_manifest
from ..progress import Progress, ensure_progress, sub_progress
from .match import height_bounds, match_pair
from .params import StereoParams
from .products import FLAGS, FLAGS_NOT_EXAMINED, PairDEM, write_pair_dem
from .scene import default_aoi_grid, footprint_xy, load_epoch_images, read_chip, sensor_kind
from .sweep import ImageChip


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


def pair_path(out_dir: os.PathLike | str, epoch: str, a: str, b: str) -> Path:
    """Where the pair-DEM of images ``a`` and ``b`` of ``epoch`` goes."""
    return Path(out_dir) / "stereo" / epoch / f"{a}__{b}.tif"


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


def pair_overlaps_aoi(a: Camera, b: Camera, grid: AOIGrid, heights: Sequence[float]) -> bool:
    """Whether the two cameras' ground footprints share some of the AOI at one of ``heights`` at least.

    A camera without a footprint (its corners do not reach the ground) counts as overlapping: the matcher decides.
    """
    from shapely.geometry import box

    aoi = box(*grid.bounds)
    for h in heights:
        try:
            o = footprint_xy(a, float(h), grid.crs).intersection(footprint_xy(b, float(h), grid.crs))
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
        if pairs == "all" or sensor_kind(a.camera) == sensor_kind(b.camera)
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
