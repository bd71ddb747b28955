"""The 2-D screen on files: two rasters, or the views of a manifest, per AOI window on geocd.tiling.

Products (``prefix`` default ``screen``) in the output folder::

    <prefix>_dissimilarity.tif   COG float32: dissimilarity (final d), grid_dissimilarity (d_g on the
                                 pixels, before superpixels), confidence (percent of the no-change
                                 pair's values below d; NaN without one), excluded (bits: 1 vegetation,
                                 2 shadow), with a QGIS style
    <prefix>_change_mask.tif     COG int8: 1 changed (d > threshold), 0 unchanged, −128 not observed
    <prefix>_changes.gpkg        layer ``changes`` (the shared schema of geocd.change.regions, method
                                 "screen <feature>"; no heights: mean/max dz and volume are NaN) + styles
    <prefix>_summary.json        threshold and how it was chosen, the null distribution, fractions, timing
    views/<epoch>_<image>.tif    (manifest) the views on the AOI grid the screen compared

**Tiling.** The screen runs tile by tile through :func:`geocd.tiling.run_tiled`. It declares
its context: the feature's receptive field plus one cell, plus two superpixel sides, rounded
up to whole cells; tiles and overlaps are whole cells, so every tile sees the same cell
lattice as the whole grid. Image stretches and the vegetation/shadow levels are measured once
on the whole image (a decimated read), not per tile. Features are then equal tiled or not;
superpixels near a seam can differ (a segment cut by the read window), which changes the
final value on a small fraction of the cells (measured in the tests).

**Manifests.** Each image is projected onto the AOI grid through its camera: on a DSM when one
is given (a true ortho, :mod:`geocd.ortho`), else on the manifest's terrain DEM (a classic
ortho — the raw view over the grid: buildings lean, which the grid features tolerate). The
pair compared is the epoch A / epoch B pair of the same sensor kind whose views are closest
in direction; the **no-change pair** is the two closest views within one epoch, whose
dissimilarities set the threshold (``false_alarm_pct``) and the confidence.
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..change.styles import discrete_pseudocolor_qml
from ..errors import ConfigError, GridError, NoOverlapError
from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress, sub_progress
from .core import ScreenParams, screen_pair
from .threshold import NullDistribution, f1_scores

CHANGE_NODATA = -128
#: what ``geocd screen`` writes (globs relative to the output folder)
PRODUCTS_GLOBS = ("screen_*", "views/*")


# ---------------------------------------------------------------------------------------------
# raster inputs
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RasterImage:
    """A georeferenced image to screen: its path, band count and names."""

    path: str
    count: int
    names: tuple[str, ...]

    @classmethod
    def open(cls, path: os.PathLike | str) -> "RasterImage":
        from ..errors import CRSError, InputFileNotFoundError
        from ..io.raster import _open

        p = Path(path)
        if not p.exists():
            raise InputFileNotFoundError(f"{p} does not exist")
        with _open(p) as ds:
            if ds.crs is None:
                raise CRSError(
                    f"{p} has no CRS: the screen compares images on a map grid; orthorectify it first (geocd ortho "
                    "IMAGE --dsm DSM), give a manifest, or give two plain images of one place with --pixel-size METRES"
                )
            names = []
            for k, (d, ci) in enumerate(zip(ds.descriptions, ds.colorinterp)):
                n = (d or ci.name or "").lower()
                names.append(n if n and n not in ("undefined", "gray", "grey") else f"b{k + 1}")
            return cls(str(p), ds.count, tuple(names))

    def grid(self) -> AOIGrid:
        from ..io.raster import _open

        with _open(self.path) as ds:
            return AOIGrid.from_raster(ds)


def _sources(img: RasterImage, bands: Sequence[int]):
    from ..tiling import RasterSource

    return [RasterSource(img.path, band=b) for b in bands]


def _pick_bands(img: RasterImage) -> list[int]:
    """Bands that matter: RGB (+ nir) of a multispectral image, else the first band."""
    if img.count >= 3:
        idx = [1, 2, 3]
        if "nir" in img.names and img.names.index("nir") + 1 not in idx:
            idx.append(img.names.index("nir") + 1)
        return idx
    return [1]


def _stretch_and_levels(img: RasterImage, bands: Sequence[int], grid: AOIGrid, max_side: int = 1024) -> dict:
    """Whole-image 1–99 % stretch per band and the vegetation/shadow levels, from a decimated read."""
    from ..io.raster import read_on_grid

    f = max(1, int(math.ceil(max(grid.shape) / max_side)))
    g = AOIGrid.from_bounds(*grid.bounds, grid.posting_m * f, grid.crs) if f > 1 else grid
    arr = np.stack([read_on_grid(img.path, g, "average" if f > 1 else "nearest", band=b) for b in bands])
    ok = np.all(np.isfinite(arr), axis=0)
    if ok.sum() < 16:
        raise NoOverlapError(f"{img.path} has no valid pixels on the grid {grid.bounds}")
    st = []
    for k in range(arr.shape[0]):
        lo, hi = np.percentile(arr[k][ok], [1, 99])
        st.append((float(lo), float(hi if hi > lo else lo + 1)))
    norm = _apply_stretch(arr, st)
    names = [img.names[b - 1] for b in bands]
    levels = {"veg_threshold": None, "shadow_median": float(np.median(norm[: min(3, len(norm))].mean(axis=0)[ok]))}
    from .core import vegetation_index

    idx = vegetation_index(norm, names)
    if idx is not None:
        from .core import _otsu

        floor = 0.2 if "nir" in names else 0.05
        levels["veg_threshold"] = max(_otsu(idx[ok]), floor)
    return {"stretch": st, "levels": levels, "names": names}


def _apply_stretch(arr: np.ndarray, stretch) -> np.ndarray:
    out = np.empty(arr.shape, np.float32)
    for k, (lo, hi) in enumerate(stretch):
        out[k] = np.clip((arr[k] - lo) / (hi - lo), 0.0, 1.0)
    return out


def context_px(params: ScreenParams, feature, gsd_m: float) -> int:
    """Pixels of context one tile needs (feature receptive field + a cell + two superpixel sides), whole cells."""
    seg = 0 if params.superpixels == "none" else 2 * params.segment_m / max(gsd_m, 1e-9)
    need = feature.context_px + feature.cell_px + seg
    c = feature.cell_px
    return int(math.ceil(need / c) * c)


# ---------------------------------------------------------------------------------------------
# the tile function
# ---------------------------------------------------------------------------------------------
_FEATURE_CACHE: dict[str, Any] = {}


def _feature(spec):
    key = spec.to_json()
    f = _FEATURE_CACHE.get(key)
    if f is None:
        f = spec.build()
        _FEATURE_CACHE.clear()
        _FEATURE_CACHE[key] = f
    return f


def screen_tile(arrays: dict, ctx) -> dict:
    """Tile function of :func:`geocd.tiling.run_tiled`: arrays ``a0..``, ``b0..`` → screen arrays."""
    P = ctx.params
    a = np.stack([arrays[f"a{k}"] for k in range(P["nbands_a"])])
    b = np.stack([arrays[f"b{k}"] for k in range(P["nbands_b"])])
    va = np.all(np.isfinite(a), axis=0)
    vb = np.all(np.isfinite(b), axis=0)
    na = _apply_stretch(np.where(np.isfinite(a), a, 0), P["stretch_a"])
    nb = _apply_stretch(np.where(np.isfinite(b), b, 0), P["stretch_b"])
    na[:, ~va] = 0.5
    nb[:, ~vb] = 0.5
    res = screen_pair(
        na,
        nb,
        gsd_m=P["gsd_m"],
        params=P["params"],
        valid_a=va,
        valid_b=vb,
        band_names_a=P["names_a"],
        band_names_b=P["names_b"],
        feature=_feature(P["params"].feature),
        normalised=True,
        levels_a=P["levels_a"],
        levels_b=P["levels_b"],
    )
    from ..tiling import TileOutput

    return TileOutput(
        arrays={
            "dissimilarity": res.dissimilarity,
            "grid_dissimilarity": res.grid_dissimilarity,
            "excluded": res.excluded.astype(np.float32),
            "valid": res.valid.astype(np.float32),
        },
        small={"unrelated_d": res.unrelated_d, "cells": int(res.cell_dissimilarity.size)},
    )


@dataclass
class ScreenRun:
    """Arrays of one screened pair on its grid (small enough to hold: the tiled products are files)."""

    grid: AOIGrid
    dissimilarity: np.ndarray
    grid_dissimilarity: np.ndarray
    excluded: np.ndarray
    valid: np.ndarray
    cell_px: int
    overlap_px: int
    n_tiles: int
    wall_s: float
    unrelated_d: float = float("nan")
    notes: list[str] = field(default_factory=list)


def screen_rasters(
    path_a: os.PathLike | str,
    path_b: os.PathLike | str,
    *,
    params: ScreenParams = ScreenParams(),
    grid: AOIGrid | None = None,
    tile_size: int = 1024,
    scheduler: str = "sync",
    out: os.PathLike | str | None = None,
    stage: str = "screen",
    progress: Progress | None = None,
) -> ScreenRun:
    """Screen two georeferenced rasters on ``grid`` (default: A's grid; B is resampled onto it), tile by tile.

    Images of different sizes, CRS or postings are resampled (bilinear) onto the grid; images
    with different band counts are compared in grey.
    """
    from ..tiling import run_tiled

    ia, ib = RasterImage.open(path_a), RasterImage.open(path_b)
    g = grid or ia.grid()
    if min(g.shape) < 8:
        raise GridError(f"the grid {g.shape} is too small to screen")
    notes = []
    if not grid:
        gb = ib.grid()
        if gb.shape != g.shape or gb.transform != g.transform or not gb.crs.equals(g.crs):
            notes.append(f"{Path(ib.path).name} resampled (bilinear) onto the grid of {Path(ia.path).name}")
    ba, bb = _pick_bands(ia), _pick_bands(ib)
    sa = _stretch_and_levels(ia, ba, g)
    sb = _stretch_and_levels(ib, bb, g)
    if len(ba) != len(bb):
        notes.append(f"the images have {ia.count} and {ib.count} bands: compared in grey")
    feat = _feature(params.feature)
    gsd = float(g.posting_m)
    ctxp = context_px(params, feat, gsd)
    c = feat.cell_px
    ts = max(c, int(round(tile_size / c)) * c)
    inputs = {f"a{k}": s for k, s in enumerate(_sources(ia, ba))}
    inputs.update({f"b{k}": s for k, s in enumerate(_sources(ib, bb))})
    P = {
        "nbands_a": len(ba),
        "nbands_b": len(bb),
        "stretch_a": sa["stretch"],
        "stretch_b": sb["stretch"],
        "names_a": sa["names"],
        "names_b": sb["names"],
        "levels_a": sa["levels"],
        "levels_b": sb["levels"],
        "gsd_m": gsd,
        "params": params,
    }
    t0 = time.perf_counter()
    run = run_tiled(
        screen_tile,
        g,
        inputs,
        overlap_cells=ctxp,
        tile_size=ts,
        params=P,
        out=out,
        stage=stage,
        scheduler=scheduler,
        progress=progress,
    )
    wall = time.perf_counter() - t0
    arr = {k: run.read(k) for k in ("dissimilarity", "grid_dissimilarity", "excluded", "valid")}
    un = [sm["unrelated_d"] for _, sm in run.smalls() if sm and np.isfinite(sm["unrelated_d"])]
    unrelated = float(np.median(un)) if un else float("nan")
    if out is not None:
        import shutil

        shutil.rmtree(
            run.store.root if hasattr(run.store, "root") else Path(out) / ".geocd-work" / stage, ignore_errors=True
        )
    return ScreenRun(
        g,
        arr["dissimilarity"],
        arr["grid_dissimilarity"],
        arr["excluded"].astype(np.uint8),
        arr["valid"] > 0.5,
        c,
        ctxp,
        run.n_tiles,
        wall,
        unrelated,
        notes,
    )


# ---------------------------------------------------------------------------------------------
# products
# ---------------------------------------------------------------------------------------------
def dissimilarity_qml(threshold: float) -> str:
    """Pseudocolour style of the dissimilarity band: transparent below the threshold."""
    t = float(threshold)
    items = [
        (t, "#ffffff", 0, f"d ≤ {t:.3g} (no change)"),
        (t + 0.1, "#fed976", 255, f"{t:.3g}–{t + 0.1:.3g}"),
        (t + 0.25, "#fd8d3c", 255, f"{t + 0.1:.3g}–{t + 0.25:.3g}"),
        ("inf", "#bd0026", 255, f"> {t + 0.25:.3g}"),
    ]
    return discrete_pseudocolor_qml(items, maximum=2.0)


def write_screen_products(
    out_dir: os.PathLike | str,
    sr: ScreenRun,
    threshold: float,
    *,
    rule: str,
    null: NullDistribution | None = None,
    method: str = "screen",
    epoch_a: str = "A",
    epoch_b: str = "B",
    prefix: str = "screen",
    min_region_m2: float = 4.0,
    summary: Mapping[str, Any] | None = None,
    overwrite: bool = True,
) -> dict[str, Path]:
    """Write the screen's COGs, change regions and summary; returns {product: path}."""
    from ..change.regions import change_regions
    from ..change.styles import write_raster_style
    from ..io.atomic import write_text_atomic
    from ..io.raster import write_cog
    from ..io.vector import qml_for, write_gpkg

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    g = sr.grid
    d = sr.dissimilarity
    conf = null.confidence_pct(d) if null is not None else np.full(d.shape, np.nan, np.float32)
    tags = {
        "method": method,
        "epoch_a": epoch_a,
        "epoch_b": epoch_b,
        "threshold": f"{threshold:.4f}",
        "threshold_rule": rule,
        "cell_px": str(sr.cell_px),
        "content": "2-D screen (Sakurada 2015 ch. 4): grid-feature dissimilarity refined by superpixels; "
        "confidence = percent of a no-change pair's dissimilarities below the value",
    }
    paths: dict[str, Path] = {}
    paths["dissimilarity"] = write_cog(
        out / f"{prefix}_dissimilarity.tif",
        {
            "dissimilarity": d,
            "grid_dissimilarity": sr.grid_dissimilarity,
            "confidence": conf,
            "excluded": np.where(sr.valid, sr.excluded, np.nan).astype(np.float32),
        },
        g,
        tags=tags,
        units={"dissimilarity": "", "grid_dissimilarity": "", "confidence": "%", "excluded": "bits"},
        band_tags=[
            {
                "long_name": "final dissimilarity: superpixel mean of d_g, max of the two dates; 0 where both "
                "dates show vegetation or shadow"
            },
            {"long_name": "d_g = |x_A - x_B| of the grid features, spread to the pixels"},
            {"long_name": "percent of the no-change pair's dissimilarities below this value"},
            {"long_name": "excluded: 1 vegetation, 2 cast shadow (bits)"},
        ],
        overwrite=overwrite,
    )
    write_raster_style(paths["dissimilarity"], dissimilarity_qml(threshold))
    changed = sr.valid & np.isfinite(d) & (d > threshold)
    mask = np.where(sr.valid & np.isfinite(d), changed.astype(np.int8), CHANGE_NODATA).astype(np.int8)
    paths["change_mask"] = write_cog(
        out / f"{prefix}_change_mask.tif",
        {"change": mask},
        g,
        nodata=CHANGE_NODATA,
        dtype="int8",
        tags=tags,
        units={"change": "class"},
        band_tags=[{"long_name": f"changed at d > {threshold:.3g}: 1 changed, 0 unchanged, -128 not observed"}],
        overview_resampling="nearest",
        overwrite=overwrite,
    )
    write_raster_style(paths["change_mask"], qml_for("change_mask"))
    mmu = max(1, int(math.ceil(min_region_m2 / g.cell_area_m2)))
    regions = change_regions(
        changed.astype(np.int8),
        np.full(d.shape, np.nan),
        g,
        confidence=conf if null is not None else None,
        method=method,
        epoch_a=epoch_a,
        epoch_b=epoch_b,
        min_cells=mmu,
        volume_confidence=False,
    )
    paths["changes"] = write_gpkg(
        out / f"{prefix}_changes.gpkg",
        {"changes": regions},
        styles={"changes": qml_for("changes")},
        overwrite=overwrite,
    )
    ok = sr.valid & np.isfinite(d)
    summ = {
        "method": method,
        "epoch_a": epoch_a,
        "epoch_b": epoch_b,
        "threshold": round(float(threshold), 4),
        "threshold_rule": rule,
        "null": null.to_dict() if null is not None else None,
        "grid": g.to_dict(),
        "cell_px": sr.cell_px,
        "overlap_px": sr.overlap_px,
        "tiles": sr.n_tiles,
        "observed_fraction": round(float(ok.mean()), 4),
        "changed_fraction": round(float(changed[ok].mean()) if ok.any() else 0.0, 5),
        "excluded_fraction": {
            "vegetation": round(float(((sr.excluded & 1) > 0)[ok].mean()) if ok.any() else 0, 4),
            "shadow": round(float(((sr.excluded & 2) > 0)[ok].mean()) if ok.any() else 0, 4),
        },
        "unrelated_d": round(float(sr.unrelated_d), 4),
        "regions": int(len(regions)),
        "seconds": round(sr.wall_s, 2),
        "seconds_per_km2": round(sr.wall_s / max(g.cell_area_m2 * g.width * g.height / 1e6, 1e-12), 2),
        "notes": list(sr.notes),
    }
    summ.update(summary or {})
    paths["summary"] = write_text_atomic(out / f"{prefix}_summary.json", json.dumps(summ, indent=2, default=str))
    return paths


def resolve_threshold(
    d_test: np.ndarray,
    *,
    threshold: float | None = None,
    null: NullDistribution | None = None,
    false_alarm_pct: float = 1.0,
    labelled: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    unrelated_d: float = float("nan"),
) -> tuple[float, str]:
    """The threshold and its rule: fixed, else from labelled pairs, else from the no-change pair (its
    quantile, then Otsu's split of the screened values above it: :func:`geocd.screen.threshold.split_above`)."""
    from .threshold import split_above

    from .threshold import threshold_best_f1

    if threshold is not None:
        return float(threshold), "fixed"
    if labelled:
        t, f = threshold_best_f1([x[0] for x in labelled], [x[1] for x in labelled])
        return t, f"best F1 ({f:.3f}) on {len(labelled)} labelled pair(s)"
    if null is not None:
        t = null.threshold(false_alarm_pct)
        rule = f"no-change pair {null.source}: {100 - false_alarm_pct:g} % quantile"
        t2 = split_above(d_test, t)
        if t2 > t:
            rule += f" ({t:.3f}), then Otsu's split of the values above it"
        return float(t2), rule
    raise ConfigError(
        "the screen needs a threshold rule: a no-change pair (--nochange A2 B2, or a manifest with two "
        "views in one epoch), a labelled pair (--labelled A B TRUTH) or --threshold VALUE"
    )


def run_screen_files(
    path_a,
    path_b,
    *,
    out: os.PathLike | str,
    params: ScreenParams = ScreenParams(),
    threshold: float | None = None,
    nochange: tuple[str, str] | None = None,
    labelled: tuple[str, str, str] | None = None,
    false_alarm_pct: float = 1.0,
    tile_size: int = 1024,
    scheduler: str = "sync",
    prefix: str = "screen",
    epoch_a: str = "A",
    epoch_b: str = "B",
    overwrite: bool = True,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Screen two rasters and write the products; the threshold from ``threshold``, a labelled pair or a
    no-change pair (screened the same way)."""
    from ..io.raster import read_on_grid

    prog = ensure_progress(progress)
    out = Path(out)
    n_aux = int(nochange is not None) + int(labelled is not None)
    span = 1.0 / (1 + n_aux)
    sr = screen_rasters(
        path_a,
        path_b,
        params=params,
        tile_size=tile_size,
        scheduler=scheduler,
        out=out,
        stage="screen",
        progress=sub_progress(prog, 0.0, 0.8 * span, "screen: "),
    )
    null = None
    lab = []
    k = 1
    if nochange is not None:
        nr = screen_rasters(
            nochange[0],
            nochange[1],
            params=params,
            tile_size=tile_size,
            scheduler=scheduler,
            out=out,
            stage="screen-nochange",
            progress=sub_progress(prog, 0.8 * span * k, 0.8 * span * (k + 1), "no-change pair: "),
        )
        null = NullDistribution.from_values(nr.dissimilarity, f"{Path(nochange[0]).name}/{Path(nochange[1]).name}")
        k += 1
    if labelled is not None:
        lr = screen_rasters(
            labelled[0],
            labelled[1],
            params=params,
            tile_size=tile_size,
            scheduler=scheduler,
            out=out,
            stage="screen-labelled",
            progress=sub_progress(prog, 0.8 * span * k, 0.8 * span * (k + 1), "labelled pair: "),
        )
        truth = read_on_grid(labelled[2], lr.grid, "nearest")
        lab = [(np.where(lr.valid, lr.dissimilarity, np.nan), np.nan_to_num(truth) > 0)]
    t, rule = resolve_threshold(
        sr.dissimilarity,
        threshold=threshold,
        null=null,
        false_alarm_pct=false_alarm_pct,
        labelled=lab,
        unrelated_d=sr.unrelated_d,
    )
    prog(0.85, "writing products")
    method = f"screen {params.feature.label}"
    paths = write_screen_products(
        out,
        sr,
        t,
        rule=rule,
        null=null,
        method=method,
        epoch_a=epoch_a,
        epoch_b=epoch_b,
        prefix=prefix,
        overwrite=overwrite,
        summary={"inputs": {"a": str(path_a), "b": str(path_b)}, "params": params.to_dict()},
    )
    prog(1.0, "screen done")
    return {"outputs": paths, "run": sr, "threshold": t, "rule": rule, "null": null}


# ---------------------------------------------------------------------------------------------
# manifests: views on the AOI grid
# ---------------------------------------------------------------------------------------------
def _view_direction(camera, grid: AOIGrid, h: float) -> np.ndarray:
    """Unit vector from the AOI centre towards the camera (east, north, up), from the camera protocol."""
    l, b, r, t = grid.bounds
    x, y = np.array([0.5 * (l + r)]), np.array([0.5 * (b + t)])
    pr = camera.ground_projector(x, y, grid.crs)
    c0, r0 = pr.project(np.array([h]))
    c1, r1 = pr.project(np.array([h + 10.0]))
    # the ground point under the same pixel at h + 10 m: where the pixel (c1, r1) at h lies
    lon_lat = camera.localize(c1, r1, np.array([h]))
    from pyproj import Transformer

    tr = Transformer.from_crs("EPSG:4326", grid.crs, always_xy=True)
    gx, gy = tr.transform(np.asarray(lon_lat[0]), np.asarray(lon_lat[1]))
    v = np.array([float(x[0] - gx[0]), float(y[0] - gy[0]), 10.0])
    return v / np.linalg.norm(v)


def pick_pairs(
    views_a: Sequence[Any], views_b: Sequence[Any], grid: AOIGrid, h: float, pair: tuple[str, str] | None = None
) -> tuple[tuple[Any, Any], tuple[Any, Any] | None]:
    """The cross-epoch pair (same sensor kind, closest view directions) and a within-epoch no-change pair."""
    from ..stereo.scene import sensor_kind

    dirs = {v.name: _view_direction(v.camera, grid, h) for v in [*views_a, *views_b]}

    def ang(u, w):
        return float(np.degrees(np.arccos(np.clip(np.dot(dirs[u.name], dirs[w.name]), -1, 1))))

    if pair is not None:
        try:
            cross = (next(v for v in views_a if v.name == pair[0]), next(v for v in views_b if v.name == pair[1]))
        except StopIteration:
            raise ConfigError(
                f"pair {pair} is not (epoch A image, epoch B image); images are "
                f"{[v.name for v in views_a]} and {[v.name for v in views_b]}"
            ) from None
    else:
        cands = [
            (ang(u, w) + (0 if sensor_kind(u.camera) == sensor_kind(w.camera) else 1000), u, w)
            for u in views_a
            for w in views_b
        ]
        cross = min(cands, key=lambda x: x[0])[1:]
    kind = sensor_kind(cross[0].camera)
    within = []
    for vs in (views_a, views_b):
        same = [v for v in vs if sensor_kind(v.camera) == kind]
        for i in range(len(same)):
            for j in range(i + 1, len(same)):
                within.append((ang(same[i], same[j]), same[i], same[j]))
    # the no-change pair whose view difference is closest to the compared pair's (same leaning of buildings)
    target = ang(*cross)
    nc = min(within, key=lambda x: abs(x[0] - target))[1:] if within else None
    return cross, nc


def flat_ground_height(names: Sequence[tuple[str, Any]], grid: AOIGrid) -> float:
    """The scene's ground height (m, ellipsoidal) for views without a DEM: the median of a coarse stereo match of
    two views of one epoch (else of the first two views), as the stereo pipeline places its AOI; the middle of
    the cameras' height range when nothing matches. A plane at the cameras' mid height can be hundreds of metres
    off (an RPC's height range spans its whole scene): every view is then displaced by its parallax and even a
    no-change pair looks unrelated."""
    from ..stereo.params import StereoParams
    from ..stereo.scene import ground_height_hint

    by_epoch: dict[str, list] = {}
    for e, v in names:
        by_epoch.setdefault(e, []).append(v)
    two = [vs for vs in by_epoch.values() if len(vs) >= 2]
    views = two[0] if two else [v for _, v in names]
    return float(ground_height_hint(views, grid.crs, None, StereoParams()))


def views_on_grid(
    manifest,
    names: Sequence[tuple[str, Any]],
    grid: AOIGrid,
    out: Path,
    *,
    dsm: Mapping | None = None,
    overwrite: bool = True,
    progress: Progress | None = None,
) -> dict[str, Path]:
    """Project the named views onto the grid: a true ortho on a given DSM, else a classic one on the terrain DEM."""
    from ..io.raster import read_dem
    from ..ortho import OrthoParams, fill_dsm_holes
    from ..ortho.pipeline import ortho_image

    prog = ensure_progress(progress)
    m = manifest
    heights: dict[str, np.ndarray] = {}
    paths = {}
    flat: list[float] = []  # the scene's ground height when an epoch has neither DSM nor DEM (computed once)
    for k, (epoch, v) in enumerate(names):
        prog(k / max(len(names), 1), f"view {epoch}/{v.name} on the grid")
        if epoch not in heights:
            given = dsm.get(epoch) if dsm else None
            ep = m.epoch(epoch)
            if given is not None:
                h = read_dem(given, grid=grid).to_ellipsoidal().height_m
            elif (ep.dem or m.dem) is not None:
                spec = ep.dem or m.dem
                h = read_dem(spec.path, grid=grid, vertical_datum=spec.vertical_datum).to_ellipsoidal().height_m
            else:
                if not flat:
                    flat.append(flat_ground_height(names, grid))
                h = np.full(grid.shape, flat[0], np.float32)
                warnings.warn(
                    f"epoch {epoch}: no DEM or DSM; the views are projected on a flat plane at "
                    f"{flat[0]:.0f} m (the ground height of a coarse match of two views)",
                    stacklevel=2,
                )
            heights[epoch] = fill_dsm_holes(h)[0]
        true = bool(dsm and dsm.get(epoch))
        params = OrthoParams(occlusion=true)
        p, _ = ortho_image(
            v.path,
            v.camera,
            grid,
            heights[epoch],
            out / "views" / f"{epoch}_{v.name}.tif",
            params=params,
            overwrite=overwrite,
            tags={"epoch": epoch, "surface": "given DSM (true ortho)" if true else "terrain DEM"},
        )
        paths[f"{epoch}/{v.name}"] = p["ortho"]
    prog(1.0, "views on the grid")
    return paths


def run_screen_manifest(
    manifest,
    *,
    out: os.PathLike | str | None = None,
    params: ScreenParams = ScreenParams(),
    threshold: float | None = None,
    false_alarm_pct: float = 1.0,
    pair: tuple[str, str] | None = None,
    dsm: Mapping[str, str] | None = None,
    epoch_a: str | None = None,
    epoch_b: str | None = None,
    tile_size: int = 1024,
    scheduler: str = "sync",
    grid: AOIGrid | None = None,
    posting_m: float | None = None,
    overwrite: bool = True,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Screen a manifest: its views on the AOI grid, the closest cross-epoch pair, a within-epoch no-change pair."""
    from ..io.manifest import Manifest, load_manifest
    from ..io.raster import read_dem
    from ..io.manifest import pick_epochs
    from ..stereo.scene import default_aoi_grid, load_epoch_images

    prog = ensure_progress(progress)
    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    o = Path(out) if out is not None else m.output_dir()
    ea, eb = pick_epochs(m, epoch_a, epoch_b)
    va, vb = load_epoch_images(m, ea), load_epoch_images(m, eb)
    if not va or not vb:
        raise ConfigError(f"the screen needs an image in each epoch; {ea.name} has {len(va)}, {eb.name} {len(vb)}")
    dem_median = None
    if m.dem is not None:
        dem_median = float(
            np.nanmedian(read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m)
        )
    if grid is None:
        grid = default_aoi_grid(m, {ea.name: va, eb.name: vb}, posting_m=posting_m, dem_median=dem_median)
    hr = va[0].camera.height_range() or (0.0, 0.0)
    h = dem_median if dem_median is not None else 0.5 * (hr[0] + hr[1])
    cross, nc = pick_pairs(va, vb, grid, h, pair)
    if nc is None and threshold is None:
        raise ConfigError(
            "no epoch has two views of the compared sensor kind, so there is no no-change pair to set "
            "the threshold: give --threshold, or add a second view to one epoch"
        )
    need = [(ea.name, cross[0]), (eb.name, cross[1])]
    if nc is not None:
        e_nc = ea.name if nc[0] in va else eb.name
        need += [(e_nc, v) for v in nc if (e_nc, v) not in need]
    vp = views_on_grid(m, need, grid, o, dsm=dsm, overwrite=overwrite, progress=sub_progress(prog, 0.0, 0.3, "views: "))
    pa, pb = vp[f"{ea.name}/{cross[0].name}"], vp[f"{eb.name}/{cross[1].name}"]
    sr = screen_rasters(
        pa,
        pb,
        params=params,
        grid=grid,
        tile_size=tile_size,
        scheduler=scheduler,
        out=o,
        stage="screen",
        progress=sub_progress(prog, 0.3, 0.65, "screen: "),
    )
    null = None
    if nc is not None:
        e_nc = ea.name if nc[0] in va else eb.name
        nr = screen_rasters(
            vp[f"{e_nc}/{nc[0].name}"],
            vp[f"{e_nc}/{nc[1].name}"],
            params=params,
            grid=grid,
            tile_size=tile_size,
            scheduler=scheduler,
            out=o,
            stage="screen-nochange",
            progress=sub_progress(prog, 0.65, 0.9, "no-change pair: "),
        )
        null = NullDistribution.from_values(nr.dissimilarity, f"{e_nc}: {nc[0].name}/{nc[1].name}")
    t, rule = resolve_threshold(
        sr.dissimilarity, threshold=threshold, null=null, false_alarm_pct=false_alarm_pct, unrelated_d=sr.unrelated_d
    )
    prog(0.9, "writing products")
    paths = write_screen_products(
        o,
        sr,
        t,
        rule=rule,
        null=null,
        method=f"screen {params.feature.label}",
        epoch_a=ea.name,
        epoch_b=eb.name,
        overwrite=overwrite,
        summary={
            "manifest": str(m.path or m.root),
            "pair": [cross[0].name, cross[1].name],
            "nochange_pair": [v.name for v in nc] if nc else None,
            "surface": "given DSM (true orthos)" if dsm else "terrain DEM (classic orthos)",
            "params": params.to_dict(),
        },
    )
    paths.update({f"view:{k}": v for k, v in vp.items()})
    prog(1.0, "screen done")
    return {
        "outputs": paths,
        "run": sr,
        "threshold": t,
        "rule": rule,
        "null": null,
        "grid": grid,
        "pair": (cross[0].name, cross[1].name),
        "nochange_pair": tuple(v.name for v in nc) if nc else None,
    }


def score_against(mask_changed: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> dict[str, float]:
    """Pixel precision/recall/F1 of a screen against a truth mask on the same grid."""
    return f1_scores(mask_changed, truth, valid)
