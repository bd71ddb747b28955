"""``geocd mpp`` on files: a scene manifest (orthos and DSMs made here) or two georeferenced images.

Manifest: the two epochs' images are orthorectified by :mod:`geocd.ortho` on geocd stereo's DSMs (or
given DSMs); one view per epoch is used — by default the one seen most nearly from above (smallest median
view zenith) among those covering at least 90 % of the AOI, so buildings lean the least and hide the least.
Two images: the second is resampled onto the first one's grid when their grids differ.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..errors import ConfigError, EmptyDataError, NoOverlapError
from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress, sub_progress
from .detect import detect
from .params import MPPParams
from .products import write_mpp_products


def view_quality(camera, grid: AOIGrid, height_m: float, factor: int = 8) -> tuple[float, float]:
    """(coverage of the grid, median view zenith in degrees) of a camera at a typical ground height."""
    from ..ortho import view_geometry
    from ..stereo.sweep import coarse_grid

    g = coarse_grid(grid, factor) if min(grid.shape) > 4 * factor else grid
    geo = view_geometry(camera, g, np.full(g.shape, float(height_m)))
    w, h = camera.width or 0, camera.height or 0
    inside = (geo.col >= 0) & (geo.row >= 0) & (geo.col < w) & (geo.row < h)
    zen = geo.view_zenith_deg[inside]
    return float(inside.mean()), float(np.median(zen)) if zen.size else 90.0


def choose_view(images: Sequence[Any], grid: AOIGrid, height_m: float, min_coverage: float = 0.9) -> Any:
    """The most nearly vertical view among those covering ``min_coverage`` of the grid (else the widest)."""
    q = [(im, *view_quality(im.camera, grid, height_m)) for im in images]
    full = [x for x in q if x[1] >= min_coverage]
    if full:
        return min(full, key=lambda x: x[2])[0]
    return max(q, key=lambda x: x[1])[0]


def _change_prior(path: os.PathLike | str, grid: AOIGrid) -> np.ndarray:
    """3-D change evidence in [0, 1] from a geocd change raster (band ``confidence``, %) or any 0–1 / 0–100 raster."""
    from ..io.raster import _open, reproject_band

    with _open(path) as ds:
        names = list(ds.descriptions)
        band = names.index("confidence") + 1 if "confidence" in names else 1
        a = reproject_band(ds, band, grid, "nearest")
    scale = 100.0 if np.nanmax(a) > 1.0 else 1.0
    return np.clip(np.where(np.isfinite(a), a / scale, 0.5), 0.0, 1.0).astype(np.float32)


def dsm_smoothing(path: os.PathLike | str) -> int | None:
    """The surface median (cells) a geocd DSM or pair-DEM was made with, from its tags; None when it does not say
    (another program's DSM). A pair-DEM whose stereo used the default median (the matching window) returns its
    window."""
    from ..io.raster import _open
    from ..stereo.params import surface_median_cells

    with _open(path) as ds:
        tags = ds.tags()
    if "surface_median_cells" in tags:
        return int(tags["surface_median_cells"])
    try:
        prm = json.loads(tags.get("meta", "{}") or "{}").get("params") or {}
    except ValueError:
        return None
    return surface_median_cells(prm) if prm else None


def _filled_band(path: os.PathLike | str, grid: AOIGrid) -> np.ndarray | None:
    """The cells of a DSM whose height its producer interpolated (a band described "filled", as geocd ortho
    writes), on ``grid``; None when the file has no such band."""
    from ..io.raster import _open, reproject_band

    with _open(path) as ds:
        names = [str(d or "").strip().lower() for d in ds.descriptions]
        if "filled" not in names:
            return None
        return reproject_band(ds, names.index("filled") + 1, grid, "nearest") > 0.5


def _warn_smoothed(paths) -> list[str]:
    """Notes (and warnings) for given DSMs made with a surface median: the height cues measure the DSM's noise."""
    notes = []
    for path in paths:
        if path is None:
            continue
        k = dsm_smoothing(path)
        if k is not None and k > 1:
            msg = (
                f"DSM {Path(path).name} was made with a {k}-cell surface median: the height cues take their "
                "tolerances from the DSM's own noise, which the median smooths away (docs/mpp.md, 'The DSM's "
                "surface median'); make it with geocd stereo --surface-median 1, or give geocd mpp the manifest and "
                "let it make the DSMs"
            )
            warnings.warn(msg, UserWarning, stacklevel=3)
            notes.append(msg)
    return notes


def run_mpp_manifest(
    manifest,
    *,
    out_dir: os.PathLike | str | None = None,
    epoch_a: str | None = None,
    epoch_b: str | None = None,
    view_a: str | None = None,
    view_b: str | None = None,
    dsm: dict | None = None,
    method: str = "ED",
    params: MPPParams = MPPParams(),
    height: str = "auto",
    change_prior: os.PathLike | str | None = None,
    posting_m: float | None = None,
    overwrite: bool = True,
    stereo_params=None,
    pair_dems: Mapping[str, Sequence[Any]] | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Orthos of one view per epoch (geocd ortho, stereo DSMs) → marked point process → layers.

    ``stereo_params`` (a :class:`geocd.stereo.StereoParams`) make the DSMs when none is given. Default: geocd
    stereo's with each cell's own match (no surface median, as ``geocd run``): the height cues measure the DSM's
    noise on the DSM itself (plane-fit residuals of its ground cells), and a median over the matching window
    smooths that noise away (docs/mpp.md, "The DSM's surface median").

    ``pair_dems`` ({epoch: [PairDEM or file, ...]}): an epoch's pair-DEMs from an earlier geocd stereo or geocd
    run on this run's AOI grid (``geocd run``'s are those of the default ``stereo_params``); its DSM is their
    median without matching its images again (:func:`geocd.ortho.pipeline.run_ortho`)."""
    from ..io.manifest import Manifest, load_manifest
    from ..io.raster import read_band, read_dem
    from ..ortho import OrthoParams
    from ..ortho.pipeline import run_ortho
    from ..io.manifest import pick_epochs
    from ..stereo.params import change_stereo_params
    from ..stereo.params import StereoParams
    from ..stereo.scene import default_aoi_grid, load_epoch_images

    prog = ensure_progress(progress)
    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    ea, eb = pick_epochs(m, epoch_a, epoch_b)
    out = Path(out_dir) if out_dir is not None else m.output_dir()
    ims = {e.name: load_epoch_images(m, e) for e in (ea, eb)}
    dem_median = None
    if m.dem is not None:
        dem_median = float(
            np.nanmedian(read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m)
        )
    grid = default_aoi_grid(m, ims, posting_m=posting_m, dem_median=dem_median, params=StereoParams())
    if dem_median is None:
        rng_h = ims[ea.name][0].camera.height_range() or (0.0, 0.0)
        dem_median = 0.5 * (rng_h[0] + rng_h[1])
    chosen = {}
    for e, want in ((ea, view_a), (eb, view_b)):
        if want:
            found = [im for im in ims[e.name] if im.name == want]
            if not found:
                raise ConfigError(
                    f"view {want!r} is not an image of epoch {e.name!r}; its images are "
                    f"{[im.name for im in ims[e.name]]}"
                )
            chosen[e.name] = found[0]
        else:
            chosen[e.name] = choose_view(ims[e.name], grid, dem_median)
    prog(0.02, f"views: {chosen[ea.name].name}, {chosen[eb.name].name}")
    use_h = height == "on" or (height == "auto" and (dsm or all(len(e.images) >= 2 for e in (ea, eb))))
    orth = run_ortho(
        m,
        epochs=[ea.name, eb.name],
        images=[chosen[ea.name].name, chosen[eb.name].name],
        out_dir=out,
        dsm=dsm,
        grid=grid,
        params=OrthoParams(),
        overwrite=overwrite,
        stereo_params=stereo_params if stereo_params is not None else change_stereo_params(),
        pair_dems=pair_dems,
        progress=sub_progress(prog, 0.02, 0.5, "ortho: "),
    )
    ra = orth["results"][f"{ea.name}/{chosen[ea.name].name}"]
    rb = orth["results"][f"{eb.name}/{chosen[eb.name].name}"]
    notes = [
        f"views: {chosen[ea.name].name} (epoch {ea.name}), {chosen[eb.name].name} (epoch {eb.name})",
        f"DSMs: {orth['dsm_source']}",
    ]
    dsm_a = dsm_b = ground = filled_a = filled_b = None
    if use_h:
        dsm_a, _ = read_band(orth["outputs"][f"{ea.name}/dsm"], 1)
        dsm_b, _ = read_band(orth["outputs"][f"{eb.name}/dsm"], 1)
        # the terrain geocd ortho put into the stereo's holes: a roof hole is no pit down to the ground
        filled_a = _filled_band(orth["outputs"][f"{ea.name}/dsm"], grid)
        filled_b = _filled_band(orth["outputs"][f"{eb.name}/dsm"], grid)
        if m.dem is not None:
            ground = read_dem(m.dem.path, grid=grid, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m
            notes.append(f"ground: the manifest's DEM {m.dem.path}")
        else:
            notes.append("ground: progressive morphological filter of each DSM (geocd.terrain)")
    p = params.replace(height="and" if use_h else "off")
    cp = None
    if change_prior is not None:
        cp = _change_prior(change_prior, grid)
        if p.gamma_3d <= 0:
            p = p.replace(gamma_3d=1.0)
        notes.append(f"3-D change prior: {change_prior}")
    det = detect(
        ra.values,
        rb.values,
        grid.posting_m,
        p,
        method=method,
        valid_a=ra.observed,
        valid_b=rb.observed,
        dsm_a=dsm_a,
        dsm_b=dsm_b,
        ground_m=ground,
        filled_a=filled_a,
        filled_b=filled_b,
        change_prior=cp,
        progress=sub_progress(prog, 0.5, 0.95, "mpp: "),
    )
    if dsm and use_h:
        notes += _warn_smoothed(dsm.values() if isinstance(dsm, dict) else [dsm])
    det.notes = notes + det.notes
    paths = write_mpp_products(
        out / "mpp",
        det,
        grid,
        epoch_a=ea.name,
        epoch_b=eb.name,
        images=(ra.values, rb.values, ra.observed, rb.observed),
        provenance={
            "manifest": str(m.path or m.root),
            "params": p.to_dict(),
            "views": {ea.name: chosen[ea.name].name, eb.name: chosen[eb.name].name},
        },
        overwrite=overwrite,
    )
    paths.update({f"ortho:{k}": v for k, v in orth["outputs"].items()})
    prog(1.0, "done")
    return {"outputs": paths, "detection": det, "grid": grid, "params": p}


def read_pair(image_a: os.PathLike | str, image_b: os.PathLike | str, posting_m: float | None = None):
    """Two georeferenced rasters on one grid (A's, or A's extent at ``posting_m``) → (a, valid_a, b, valid_b,
    grid, notes). B is resampled (bilinear) onto the grid when its grid differs."""
    from rasterio.warp import reproject
    from rasterio.enums import Resampling
    from rasterio.crs import CRS as RioCRS

    from ..io.raster import _open, read_image

    notes = []
    with _open(image_a) as ds:
        if ds.crs is None:
            raise ConfigError(
                f"{image_a} has no georeference; give orthoimages (geocd ortho) or georeferenced rasters, or --pixel-size METRES for two plain images of one place"
            )
        grid = AOIGrid.from_raster(ds)
    if posting_m is not None and abs(posting_m - grid.posting_m) > 1e-9:
        grid = AOIGrid.from_bounds(*grid.bounds, posting_m, grid.crs)
    out = []
    for path in (image_a, image_b):
        img = read_image(path)
        with _open(path) as ds:
            if ds.crs is None:
                raise ConfigError(
                    f"{path} has no georeference; give orthoimages (geocd ortho) or georeferenced rasters, or --pixel-size METRES for two plain images of one place"
                )
            same = AOIGrid.from_raster(ds) == grid
            src_t, src_crs = ds.transform, ds.crs
        if same:
            out += [img.data, img.valid]
            continue
        data = np.full((img.bands,) + grid.shape, np.nan, np.float32)
        src = np.where(img.valid[None], img.data.astype(np.float32), np.nan)
        for k in range(img.bands):
            reproject(
                src[k],
                data[k],
                src_transform=src_t,
                src_crs=src_crs,
                src_nodata=np.nan,
                dst_transform=grid.transform,
                dst_crs=RioCRS.from_wkt(grid.crs.to_wkt()),
                dst_nodata=np.nan,
                resampling=Resampling.bilinear,
            )
        valid = np.all(np.isfinite(data), axis=0)
        if not valid.any():
            raise NoOverlapError(f"{path} does not overlap {image_a}; the two images must cover the same area")
        notes.append(f"{Path(path).name} resampled (bilinear) onto the grid of {Path(image_a).name}")
        out += [data, valid]
    if out[1].shape != out[3].shape:
        raise EmptyDataError("internal: the two images did not end on one grid")
    return out[0], out[1], out[2], out[3], grid, notes


def run_mpp_images(
    image_a: os.PathLike | str,
    image_b: os.PathLike | str,
    *,
    out_dir: os.PathLike | str,
    dsm_a: os.PathLike | str | None = None,
    dsm_b: os.PathLike | str | None = None,
    ground: os.PathLike | str | None = None,
    method: str = "ED",
    params: MPPParams = MPPParams(),
    change_prior: os.PathLike | str | None = None,
    posting_m: float | None = None,
    epoch_names: tuple[str, str] = ("A", "B"),
    overwrite: bool = True,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Two georeferenced images (e.g. orthos) → marked point process → layers."""
    from ..io.atomic import protect_inputs
    from ..io.raster import read_dem

    protect_inputs(image_a, image_b)
    a, va, b, vb, grid, notes = read_pair(image_a, image_b, posting_m)
    if (dsm_a is None) != (dsm_b is None):
        raise ConfigError("give a DSM for both dates (--dsm-a and --dsm-b) or for neither")
    da = db = gr = fa = fb = None
    if dsm_a is not None:
        da = read_dem(dsm_a, grid=grid).to_ellipsoidal().height_m
        db = read_dem(dsm_b, grid=grid).to_ellipsoidal().height_m
        fa, fb = _filled_band(dsm_a, grid), _filled_band(dsm_b, grid)
        if ground is not None:
            gr = read_dem(ground, grid=grid).to_ellipsoidal().height_m
    p = params.replace(height="and" if da is not None else "off")
    cp = None
    if change_prior is not None:
        cp = _change_prior(change_prior, grid)
        if p.gamma_3d <= 0:
            p = p.replace(gamma_3d=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        det = detect(
            a,
            b,
            grid.posting_m,
            p,
            method=method,
            valid_a=va,
            valid_b=vb,
            dsm_a=da,
            dsm_b=db,
            ground_m=gr,
            filled_a=fa,
            filled_b=fb,
            change_prior=cp,
            progress=progress,
        )
    if dsm_a is not None:
        notes += _warn_smoothed([dsm_a, dsm_b])
    det.notes = notes + det.notes
    paths = write_mpp_products(
        out_dir,
        det,
        grid,
        epoch_a=epoch_names[0],
        epoch_b=epoch_names[1],
        images=(a, b, va, vb),
        provenance={"image_a": str(image_a), "image_b": str(image_b), "params": p.to_dict()},
        overwrite=overwrite,
    )
    return {"outputs": paths, "detection": det, "grid": grid, "params": p}
