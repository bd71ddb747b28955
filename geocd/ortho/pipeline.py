"""Orthoimage files: image windows in, Cloud-Optimized GeoTIFFs out.

Per image ``<name>``::

    <name>.tif          COG, the image's bands in their own dtype on the AOI grid; GDAL internal mask
                        (and NaN for float bands) = not observed: occluded, outside the image, no height
    <name>.qml          QGIS style (grey or RGB, stretched on the 2–98 % of the observed values)
    <name>_status.tif   COG uint8 per cell: 0 seen, 1 seen (height filled in a DSM hole), 2 occluded,
                        3 outside the image / image nodata, 4 no DSM height (paletted, with .qml)
    <name>_view.tif     COG float32 (optional): view_zenith_deg, view_azimuth_deg, incidence_deg, px_per_cell

:func:`run_ortho` does every image of a manifest's epochs with one DSM per
epoch: given (``dsm=``), else geocd stereo's (median of the epoch's pair-DEMs, matched here or
given as ``pair_dems=`` from an earlier geocd stereo or geocd run), else the epoch's or the
manifest's DEM (a terrain DEM gives a classic ortho, not a true one: buildings lean; a warning
says so).
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..camera import Camera
from ..errors import ConfigError, GridError
from ..geodesy import AOIGrid
from ..io.raster import write_cog
from ..progress import Progress, ensure_progress, sub_progress
from ..stereo.params import surface_median_cells
from ..stereo.products import PairDEM, read_pair_dem
from ..stereo.surface import epoch_surface
from .core import (
    NO_HEIGHT,
    OCCLUDED,
    OUTSIDE_IMAGE,
    SEEN,
    SEEN_FILLED_HEIGHT,
    STATUS_LABELS,
    OrthoParams,
    OrthoResult,
    fill_dsm_holes,
    orthorectify,
)

STATUS_COLOURS = {
    SEEN: "#1a9641",
    SEEN_FILLED_HEIGHT: "#a6d96a",
    OCCLUDED: "#d7191c",
    OUTSIDE_IMAGE: "#bdbdbd",
    NO_HEIGHT: "#404040",
}


# ---------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------
def read_image_for_grid(
    path: os.PathLike | str, camera: Camera, grid: AOIGrid, lo_m: float, hi_m: float, margin_px: int = 8
):
    """Read the window of an image that the grid sees between two heights.

    Returns
    -------
    data (bands, rows, cols) native dtype, valid bool (rows, cols), col0, row0, band names (list of str)
    """
    from ..io.raster import _open
    from ..stereo.scene import read_grid_window

    with _open(path) as ds:
        W, H = ds.width, ds.height
        desc = list(ds.descriptions)
        interp = [ci.name for ci in ds.colorinterp]
    img, c0, r0 = read_grid_window(path, camera, grid, lo_m, hi_m, W, H, margin_px=margin_px, check="the DSM")
    names = [
        d if d else (i if i not in ("undefined", "gray") or img.bands > 1 else "gray") for d, i in zip(desc, interp)
    ]
    names = [n if n != "undefined" else f"b{k + 1}" for k, n in enumerate(names)]
    return img.data, img.valid, c0, r0, names


# ---------------------------------------------------------------------------------------------
# styles
# ---------------------------------------------------------------------------------------------
_QML_HEAD = """<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis version="3.22.16-Białowieża" styleCategories="AllStyleCategories" hasScaleBasedVisibilityFlag="0" minScale="1e+08" maxScale="0">
  <pipe>
    <provider>
      <resampling zoomedInResamplingMethod="nearestNeighbour" zoomedOutResamplingMethod="nearestNeighbour" enabled="false" maxOversampling="2"/>
    </provider>
"""
_QML_TAIL = """    <brightnesscontrast brightness="0" contrast="0" gamma="1"/>
    <huesaturation saturation="0" colorizeOn="0" colorizeRed="255" colorizeGreen="128" colorizeBlue="128" colorizeStrength="100" grayscaleMode="0" invertColors="0"/>
    <rasterresampler maxOversampling="2"/>
    <resamplingStage>resamplingFilter</resamplingStage>
  </pipe>
  <blendMode>0</blendMode>
</qgis>
"""
_MINMAX = """      <minMaxOrigin>
        <limits>CumulativeCut</limits>
        <extent>WholeRaster</extent>
        <statAccuracy>Estimated</statAccuracy>
        <cumulativeCutLower>0.02</cumulativeCutLower>
        <cumulativeCutUpper>0.98</cumulativeCutUpper>
        <stdDevFactor>2</stdDevFactor>
      </minMaxOrigin>
"""


def _stretch(band: np.ndarray, observed: np.ndarray) -> tuple[float, float]:
    v = band[observed].astype(np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(v, [2, 98])
    return float(lo), float(hi if hi > lo else lo + 1)


def ortho_qml(values: np.ndarray, observed: np.ndarray) -> str:
    """Grey (1 band) or RGB (first three bands) style, stretched on the 2–98 % of the observed values."""

    def ce(tag: str, band: int, lo: float, hi: float) -> str:
        # QGIS reads minValue/maxValue/algorithm as direct children of the band's element (what it writes itself);
        # nested one level deeper they are ignored and a 16-bit image opens black (0–65535, no stretch)
        return (
            f"      <{tag}>\n        <minValue>{lo:g}</minValue>\n        <maxValue>{hi:g}</maxValue>\n"
            f"        <algorithm>StretchToMinimumMaximum</algorithm>\n      </{tag}>\n"
        )

    if values.shape[0] >= 3:
        st = [_stretch(values[k], observed) for k in range(3)]
        body = (
            '    <rasterrenderer type="multibandcolor" redBand="1" greenBand="2" blueBand="3" opacity="1" '
            'alphaBand="-1" nodataColor="">\n      <rasterTransparency/>\n'
            + _MINMAX
            + ce("redContrastEnhancement", 1, *st[0])
            + ce("greenContrastEnhancement", 2, *st[1])
            + ce("blueContrastEnhancement", 3, *st[2])
            + "    </rasterrenderer>\n"
        )
    else:
        lo, hi = _stretch(values[0], observed)
        body = (
            '    <rasterrenderer type="singlebandgray" grayBand="1" gradient="BlackToWhite" opacity="1" '
            'alphaBand="-1" nodataColor="">\n      <rasterTransparency/>\n'
            + _MINMAX
            + ce("contrastEnhancement", 1, lo, hi)
            + "    </rasterrenderer>\n"
        )
    return _QML_HEAD + body + _QML_TAIL


def status_qml() -> str:
    """Paletted style of the status band (seen cells transparent-ish green, occluded red)."""
    entries = "\n".join(
        f'        <paletteEntry value="{k}" color="{STATUS_COLOURS[k]}" alpha="{90 if k == SEEN else 255}" '
        f'label="{STATUS_LABELS[k]}"/>'
        for k in STATUS_LABELS
    )
    body = (
        '    <rasterrenderer type="paletted" band="1" opacity="1" alphaBand="-1" nodataColor="">\n'
        "      <rasterTransparency/>\n      <colorPalette>\n" + entries + "\n      </colorPalette>\n"
        '      <colorramp type="randomcolors" name="[source]"/>\n    </rasterrenderer>\n'
    )
    return _QML_HEAD + body + _QML_TAIL


# ---------------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------------
def write_ortho(
    path: os.PathLike | str,
    result: OrthoResult,
    grid: AOIGrid,
    *,
    band_names: Sequence[str] | None = None,
    tags: Mapping[str, Any] | None = None,
    view_bands: bool = False,
    overwrite: bool = True,
) -> dict[str, Path]:
    """Write an orthoimage, its status band and (optionally) its view geometry; returns {product: path}."""
    from ..change.styles import write_raster_style

    p = Path(path)
    vals = result.values
    names = list(band_names) if band_names else [f"b{k + 1}" for k in range(vals.shape[0])]
    if len(names) != vals.shape[0]:
        names = [f"b{k + 1}" for k in range(vals.shape[0])]
    t = {
        "method": "geocd ortho (true ortho)",
        "occlusion_tol_m": f"{result.occlusion_tol_m:.3f}",
        "status_fractions": json.dumps(result.fractions()),
    }
    if result.notes:
        t["notes"] = "; ".join(result.notes)
    t.update(tags or {})
    paths: dict[str, Path] = {}
    paths["ortho"] = write_cog(p, dict(zip(names, vals)), grid, tags=t, mask=result.observed, overwrite=overwrite)
    write_raster_style(paths["ortho"], ortho_qml(vals, result.observed))
    stem = p.with_suffix("")
    paths["status"] = write_cog(
        f"{stem}_status.tif",
        {"status": result.status},
        grid,
        dtype="uint8",
        tags={**t, "categories": json.dumps({str(k): v for k, v in STATUS_LABELS.items()})},
        overview_resampling="nearest",
        overwrite=overwrite,
    )
    write_raster_style(paths["status"], status_qml())
    if view_bands:
        g = result.geometry
        paths["view"] = write_cog(
            f"{stem}_view.tif",
            {
                "view_zenith_deg": g.view_zenith_deg,
                "view_azimuth_deg": g.view_azimuth_deg,
                "incidence_deg": g.incidence_deg,
                "px_per_cell": g.px_per_cell,
            },
            grid,
            tags=t,
            overwrite=overwrite,
        )
    return paths


def ortho_image(
    image_path: os.PathLike | str,
    camera: Camera,
    grid: AOIGrid,
    dsm_m: np.ndarray,
    out_path: os.PathLike | str,
    *,
    params: OrthoParams = OrthoParams(),
    dsm_filled: np.ndarray | None = None,
    view_bands: bool = False,
    overwrite: bool = True,
    tags: Mapping[str, Any] | None = None,
) -> tuple[dict[str, Path], OrthoResult]:
    """Orthorectify one image file onto the grid and write its products."""
    from ..io.atomic import protect_inputs

    protect_inputs(image_path)
    ok = np.isfinite(dsm_m)
    if not ok.any():
        raise ConfigError("the DSM has no valid height on the grid")
    lo, hi = float(np.nanmin(dsm_m)), float(np.nanmax(dsm_m))
    data, valid, c0, r0, names = read_image_for_grid(image_path, camera, grid, lo, hi)
    res = orthorectify(data, camera, grid, dsm_m, valid=valid, col0=c0, row0=r0, params=params, dsm_filled=dsm_filled)
    t = {"source_image": str(image_path), "params": params.to_json()}
    t.update(tags or {})
    paths = write_ortho(out_path, res, grid, band_names=names, tags=t, view_bands=view_bands, overwrite=overwrite)
    return paths, res


# ---------------------------------------------------------------------------------------------
# epoch DSMs and the manifest run
# ---------------------------------------------------------------------------------------------
def _given_pair_dems(items: Sequence[Any], grid: AOIGrid, epoch: str) -> list:
    """Pair-DEMs (objects or files, read here) of one epoch, each checked to be on ``grid``."""
    pds = [p if isinstance(p, PairDEM) else read_pair_dem(p) for p in items]
    for p in pds:
        if p.grid != grid:
            raise GridError(
                f"pair-DEM {p.name or '?'} of epoch {epoch!r} is on a {p.grid.width} × {p.grid.height}-cell grid at "
                f"{p.grid.transform.c:.2f}, {p.grid.transform.f:.2f} ({p.grid.posting_m:g} m), not the run's "
                f"{grid.width} × {grid.height} cells at {grid.transform.c:.2f}, {grid.transform.f:.2f} "
                f"({grid.posting_m:g} m); give pair-DEMs matched on the run's AOI grid, or none"
            )
    return pds


def run_ortho(
    manifest,
    *,
    epochs: Sequence[str] | None = None,
    images: Sequence[str] | None = None,
    out_dir: os.PathLike | str | None = None,
    dsm: os.PathLike | str | Mapping[str, Any] | None = None,
    dsm_source: str = "auto",
    grid: AOIGrid | None = None,
    posting_m: float | None = None,
    params: OrthoParams = OrthoParams(),
    view_bands: bool = False,
    overwrite: bool = True,
    stereo_params=None,
    pair_dems: Mapping[str, Sequence[Any]] | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Orthoimages of a manifest's images, one DSM per epoch.

    Parameters
    ----------
    manifest : Manifest or path
    epochs, images : restrict to these epochs / image names (default: all)
    dsm : a DSM file for every epoch, or {epoch: path}; heights are read onto the grid
    dsm_source : "auto" (the given DSM, else geocd stereo when the epoch has two images, else the
        epoch's or the manifest's DEM), "stereo", or "dem"
    grid : AOI grid (default: the manifest's AOI, as geocd stereo makes it)
    pair_dems : {epoch: [PairDEM or pair-DEM file, ...]}, optional
        An epoch's pair-DEMs from an earlier geocd stereo or geocd run on ``grid`` (e.g. its
        ``stereo/<epoch>/*.tif``): with ``dsm_source`` "auto" or "stereo" and no given DSM, the epoch's
        DSM is their median, as if matched here, without matching its images again. The DSM's
        ``surface_median_cells`` tag is the largest surface median their parameters name.

    Returns
    -------
    dict: outputs {"<epoch>/<image>": path, ...}, grid, dsm_source {epoch: str}, fractions {image: {...}},
    results {"<epoch>/<image>": OrthoResult}
    """
    from ..io.manifest import Manifest, load_manifest
    from ..io.raster import read_dem
    from ..stereo.params import StereoParams
    from ..stereo.pipeline import run_stereo
    from ..stereo.scene import default_aoi_grid, load_epoch_images

    if dsm_source not in ("auto", "stereo", "dem"):
        raise ConfigError(f"dsm_source must be auto, stereo or dem, got {dsm_source!r}")
    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    prog = ensure_progress(progress)
    sel = [m.epoch(e) for e in epochs] if epochs else list(m.epochs)
    out = Path(out_dir) if out_dir is not None else m.output_dir()
    ims = {e.name: [im for im in load_epoch_images(m, e) if not images or im.name in images] for e in sel}
    if images:
        missing = set(images) - {im.name for v in ims.values() for im in v}
        if missing:
            raise ConfigError(
                f"images {sorted(missing)} are not in the selected epochs of the manifest; "
                f"images are {[im.name for v in ims.values() for im in v]}"
            )
    ims = {k: v for k, v in ims.items() if v}
    sp = stereo_params or StereoParams()
    if grid is None:
        dem_median = None
        if m.dem is not None:
            dem_median = float(
                np.nanmedian(read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m)
            )
        grid = default_aoi_grid(m, ims, posting_m=posting_m, dem_median=dem_median, params=sp)
    prior = None
    if m.dem is not None:
        prior = read_dem(m.dem.path, grid=grid, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m
    outputs: dict[str, Path] = {}
    results: dict[str, OrthoResult] = {}
    sources: dict[str, str] = {}
    smoothing: dict[str, int] = {}  # the stereo's surface median (cells) behind each epoch's DSM
    n_total = sum(len(v) for v in ims.values())
    done = 0
    for e in sel:
        if e.name not in ims:
            continue
        given = dsm.get(e.name) if isinstance(dsm, Mapping) else dsm
        h = None
        if given is not None and dsm_source in ("auto", "dem"):
            h = read_dem(given, grid=grid).to_ellipsoidal().height_m
            sources[e.name] = f"given: {given}"
        elif dsm_source in ("auto", "stereo") and pair_dems and pair_dems.get(e.name):
            pds = _given_pair_dems(pair_dems[e.name], grid, e.name)
            h = epoch_surface(pds)
            sources[e.name] = f"geocd stereo: median of {len(pds)} given pair-DEMs"
            known = [surface_median_cells(p.meta["params"]) for p in pds if p.meta.get("params")]
            if known:
                smoothing[e.name] = max(known)
        elif dsm_source in ("auto", "stereo") and len(e.images) >= 2:
            f0 = done / max(n_total, 1)
            st = run_stereo(
                m,
                epochs=[e.name],
                out_dir=out,
                params=sp,
                grid=grid,
                keep_arrays=True,
                pairs="same-kind",
                overwrite=overwrite,
                progress=sub_progress(prog, f0, f0 + 0.5 * len(ims[e.name]) / max(n_total, 1), f"{e.name} stereo: "),
            )
            h = epoch_surface(list(st["pairs"].values()))
            sources[e.name] = f"geocd stereo: median of {len(st['pairs'])} pair-DEMs"
            smoothing[e.name] = sp.median_size
        else:
            spec = e.dem or m.dem
            if spec is None:
                raise ConfigError(
                    f"no DSM for epoch {e.name!r}: give one (--dsm), or two images for geocd stereo, "
                    "or a DEM in the manifest"
                )
            h = read_dem(spec.path, grid=grid, vertical_datum=spec.vertical_datum).to_ellipsoidal().height_m
            sources[e.name] = f"DEM: {spec.path}"
            if spec is m.dem:
                warnings.warn(
                    f"epoch {e.name}: orthorectified on the terrain DEM {spec.path}, not a surface model: "
                    "buildings lean and occlusions are not found (a classic, not a true ortho)",
                    stacklevel=2,
                )
        filled_h, hole = fill_dsm_holes(h, prior)
        dsm_path = write_cog(
            out / "ortho" / e.name / f"dsm_{e.name}.tif",
            {"height_m": filled_h.astype(np.float32), "filled": hole.astype(np.float32)},
            grid,
            tags={
                "source": sources[e.name],
                "vertical_datum": "ellipsoid",
                **({"surface_median_cells": str(smoothing[e.name])} if e.name in smoothing else {}),
            },
            overwrite=overwrite,
        )
        outputs[f"{e.name}/dsm"] = dsm_path
        for im in ims[e.name]:
            f0 = done / max(n_total, 1)
            prog(f0, f"ortho {e.name}/{im.name}")
            paths, res = ortho_image(
                im.path,
                im.camera,
                grid,
                filled_h,
                out / "ortho" / e.name / f"{im.name}.tif",
                params=params,
                dsm_filled=hole,
                view_bands=view_bands,
                overwrite=overwrite,
                tags={"epoch": e.name, "dsm": sources[e.name]},
            )
            outputs[f"{e.name}/{im.name}"] = paths["ortho"]
            results[f"{e.name}/{im.name}"] = res
            done += 1
    prog(1.0, "ortho done")
    return {
        "outputs": outputs,
        "grid": grid,
        "dsm_source": sources,
        "results": results,
        "fractions": {k: r.fractions() for k, r in results.items()},
    }
