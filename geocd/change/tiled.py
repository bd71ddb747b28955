"""The self-consistency change test tile by tile (:mod:`geocd.tiling`): whole scenes, bounded memory, resumable.

:func:`change_test_tiled` wraps :func:`geocd.consistency.change_test`: every tile reads its window
of each reconstruction (pair-DEM GeoTIFFs from ``geocd stereo``, or a DEM standing for an epoch)
and runs the test there with the whole-scene inputs fixed:

* the **model** (significance curves, region null) is whole-scene already;
* the **vertical offsets** (a median over every pair of reconstructions) are reduced over the
  tiles first, on every cell up to ``TilingParams.sample_cells`` cells (a fixed hashed
  subsample beyond) — :func:`geocd.consistency.vertical_offsets` on the gathered cells;
* the **cell test**'s minimum mapping unit (groups smaller than ``min_region_cells`` dropped) is
  local: tiles carry ``min_region_cells − 1`` cells of overlap;
* the **region test** clusters cells of the whole scene: each tile labels its candidate cells,
  :mod:`geocd.tiling.regions` joins the labels across seams and sums their evidence, the region
  null ranks each merged region, and a second pass writes every cell's region confidence.

Up to ``exact_grid_cells`` the per-cell results are gathered and written by
:func:`geocd.change.products.write_change_products` (identical products); beyond, rasters are
written tile by tile and the ``changes`` layer comes from regions merged across seams (volume
σ from the same correlated-error formula, the region's confidence the median over its cells).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..consistency import (
    CHANGE_NODATA,
    ChangeParams,
    ChangeResult,
    DEMAsEpoch,
    SelfConsistencyModel,
    change_test,
    PairCalibration,
    _comparison_arrays,
    apply_offsets,
    fit_pair_calibration,
    model_learned_on,
    vertical_offsets,
)
from ..errors import ConfigError, GridError, UnsupportedFormatError
from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress, sub_progress
from ..tiling import (
    WORK_DIR,
    RasterProduct,
    RasterSource,
    TileGrid,
    TileOutput,
    open_engine,
    remove_work,
    run_tiled,
    write_product,
)
from ..tiling.writer import check_assembly_room


@dataclass(frozen=True)
class Reconstruction:
    """A reconstruction on disk: a pair-DEM GeoTIFF (``kind="pair"``) or a DEM standing for an epoch.

    Use :func:`open_reconstruction`; :meth:`read` gives the PairDEM (or DEMAsEpoch) of a window.
    """

    path: str
    kind: str
    name: str
    epoch: str = ""
    bands: tuple[tuple[str, int], ...] = ()
    meta_json: str = "{}"
    cameras: tuple[str, str] = ("a", "b")
    vertical_datum: str | None = None

    @property
    def meta(self) -> dict:
        return json.loads(self.meta_json)

    def identity(self) -> dict:
        import os

        st = os.stat(self.path)
        return {
            "path": os.path.abspath(self.path),
            "size": st.st_size,
            "mtime_ns": st.st_mtime_ns,
            "kind": self.kind,
            "name": self.name,
            "datum": self.vertical_datum,
        }

    def read(self, grid: AOIGrid, window: tuple[int, int, int, int]):
        """The reconstruction on ``window`` (row0, col0, h, w) of ``grid``: what ``read_pair_dem`` /
        the ``--dem-a`` loader give, cut to the window."""
        r0, c0, h, w = window
        sub = grid.subgrid(r0, c0, h, w)
        if self.kind == "dem":
            z = RasterSource(self.path, dem=True).read(grid, window)
            if self.vertical_datum:
                from ..io.raster import DEM

                z = DEM(z, sub, self.vertical_datum).to_ellipsoidal().height_m.astype(np.float32)
            return DEMAsEpoch(z, sub, self.name)
        import rasterio
        from rasterio.windows import Window

        from ..stereo.products import PairDEM

        with rasterio.Env(GDAL_CACHEMAX=128), rasterio.open(self.path) as ds:
            arrs = {n: ds.read(i, window=Window(c0, r0, w, h)).astype(np.float32) for n, i in self.bands}
        valid = arrs.get("valid", np.isfinite(arrs["z"]).astype(np.float32)) > 0.5
        flags = arrs.get("flags")
        return PairDEM(
            z_m=arrs["z"],
            score=arrs.get("score", np.full((h, w), np.nan, np.float32)),
            g_px_per_m=arrs["g"],
            valid=valid & np.isfinite(arrs["z"]),
            grid=sub,
            name=self.name,
            camera_names=self.cameras,
            ncc=arrs.get("ncc"),
            ssd=arrs.get("ssd"),
            flags=None if flags is None else np.nan_to_num(flags).astype(np.uint8),
            epoch=self.epoch,
            meta=self.meta,
        )


def open_reconstruction(
    path,
    *,
    kind: str | None = None,
    name: str | None = None,
    epoch: str | None = None,
    vertical_datum: str | None = None,
) -> tuple[Reconstruction, AOIGrid]:
    """A :class:`Reconstruction` from its file's metadata (no pixels read), with its grid."""
    from ..io.raster import _open

    with _open(path) as ds:
        names = tuple(ds.descriptions or ())
        grid = AOIGrid.from_raster(ds)
        tags = ds.tags()
    is_pair = "z" in names and "g" in names
    kind = kind or ("pair" if is_pair else "dem")
    if kind == "pair":
        if not is_pair:
            raise UnsupportedFormatError(
                f"{path} is not a geocd stereo pair-DEM (bands z, score, g, valid, ...); make it with `geocd stereo`"
            )
        cams = tuple(json.loads(tags.get("cameras", '["a", "b"]')))
        return Reconstruction(
            str(path),
            "pair",
            name or tags.get("pair", Path(path).stem),
            epoch or tags.get("epoch", ""),
            tuple((n, i + 1) for i, n in enumerate(names) if n),
            tags.get("meta", "{}") or "{}",
            cams if len(cams) == 2 else ("a", "b"),
        ), grid
    return Reconstruction(str(path), "dem", name or Path(path).stem, epoch or "", vertical_datum=vertical_datum), grid


@dataclass(frozen=True)
class _Job:
    grid: AOIGrid
    a: tuple[Reconstruction, ...]
    b: tuple[Reconstruction, ...]
    model: SelfConsistencyModel
    params: ChangeParams
    offsets: dict
    fraction: float
    significance: str
    footprints: bool
    calibration: PairCalibration | None = None

    def cache_key(self) -> dict:
        return {
            "a": [r.identity() for r in self.a],
            "b": [r.identity() for r in self.b],
            "model": self.model.to_dict(),
            "params": self.params,
            "offsets": self.offsets,
            "fraction": self.fraction,
            "fp": self.footprints,
            "calibration": self.calibration.to_dict() if self.calibration is not None else None,
        }


class _Cells:
    """A reconstruction's values on gathered cells (1-D arrays): what :func:`vertical_offset` reads."""

    def __init__(self, name: str, z_m: np.ndarray, score: np.ndarray, valid: np.ndarray):
        self.name, self.z_m, self.score, self.valid = name, z_m, score, valid


def _sampled_core_cells(mask: np.ndarray, ctx) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(tile rows, tile cols, global linear index) of the mask's core cells, subsampled with the
    scene-wide deterministic hash when the whole-scene statistics use a fraction of the cells."""
    J = ctx.params
    core = ctx.core
    rr, cc = np.nonzero(mask[core])
    if J.fraction < 1.0:
        from ..tiling.params import keep_cells

        T0, U0 = ctx.tile.core[:2]
        keep = keep_cells(rr + T0, cc + U0, J.grid.width, J.fraction)
        rr, cc = rr[keep], cc[keep]
    rr = rr + core[0].start
    cc = cc + core[1].start
    R0, C0 = ctx.origin
    return rr, cc, (rr + R0).astype(np.int64) * J.grid.width + (cc + C0)


def _t_offsets(arrays, ctx):
    """z, score, valid of every reconstruction on the cells any of them observes (sampled)."""
    J = ctx.params
    recs = [r.read(J.grid, ctx.tile.read) for r in (*J.a, *J.b)]
    anyv = np.zeros(recs[0].z_m.shape, bool)
    for r in recs:
        anyv |= np.asarray(r.valid, bool) & np.isfinite(r.z_m)
    rr, cc, idx = _sampled_core_cells(anyv, ctx)
    return TileOutput(
        small={
            "idx": idx,
            **{f"{r.name}|z": np.asarray(r.z_m)[rr, cc] for r in recs},
            **{f"{r.name}|s": np.asarray(r.score)[rr, cc] for r in recs},
            **{f"{r.name}|v": np.asarray(r.valid)[rr, cc] for r in recs},
        }
    )


def _t_calibration(arrays, ctx):
    """Per cross-epoch comparison: Δ̃, score, slope and metres per Δ̃ unit of the observed core cells (sampled)."""
    J = ctx.params
    na = len(J.a)
    al = apply_offsets([r.read(J.grid, ctx.tile.read) for r in (*J.a, *J.b)], J.offsets)
    ea = sorted(al[:na], key=lambda r: r.name)
    eb = sorted(al[na:], key=lambda r: r.name)
    small: dict[str, Any] = {}
    for k, (p, q) in enumerate((p, q) for p in ea for q in eb):
        dt, sc, _, both, mpu, slope = _comparison_arrays(p, q, J.grid.posting_m)
        rr, cc, small[f"{k}|idx"] = _sampled_core_cells(both, ctx)
        for name, v in (("dt", dt), ("sc", sc), ("slope", slope), ("mpu", mpu)):
            small[f"{k}|{name}"] = np.asarray(v)[rr, cc]
    return TileOutput(small=small)


def _t_change(arrays, ctx):
    """The change test on a tile with the whole-scene offsets and model."""
    from ..stereo.surface import epoch_surface
    from ..tiling.regions import tile_regions

    J = ctx.params
    a = [r.read(J.grid, ctx.tile.read) for r in J.a]
    b = [r.read(J.grid, ctx.tile.read) for r in J.b]
    res = change_test(a, b, J.model, J.params, offsets=J.offsets, calibration=J.calibration)
    out = {
        "dz_m": res.dz_m,
        "dtilde": res.dtilde,
        "score": res.score,
        "confidence": res.confidence,
        "change": res.change,
        "nobs": res.n_comparisons,
        "cell_confidence": res.cell_confidence,
        "dz_sigma_m": res.dz_sigma_m,
    }
    small: dict[str, Any] = {
        "mmu": res.min_region_cells,
        "significance": res.significance,
        "comparisons": res.comparisons,
    }
    core = ctx.core
    if J.significance == "region":
        # candidate cells of the whole-scene clustering: p < α0 with the cell's sign
        alpha0 = 1.0 - float(J.model.region_null["cluster_confidence"]) / 100.0
        p = np.where(res.observed, res.p_value, 1.0)[core]
        sign = np.sign(np.nan_to_num(res.dz_m)).astype(np.int8)[core]
        cand = np.isfinite(p) & (p < alpha0)
        ev = np.where(cand, np.log(alpha0 / np.maximum(np.where(cand, p, 1.0), 1e-300)), 0.0)
        tr = tile_regions(np.where(cand, sign, 0).astype(np.int8), ev, ctx.tile, J.grid, polygons=False)
        out["cand_labels"] = tr.labels
        tr.labels = None
        small["cand"] = tr
    if J.footprints:
        out["z_a"] = epoch_surface(a)
        out["z_b"] = epoch_surface(b)
    return TileOutput(arrays=out, small=small)


def _t_region_conf(arrays, ctx):
    """Every cell's region confidence (merged regions) and the change sign at the lowest level."""
    conf_by_label, level0 = ctx.params
    t = ctx.tile
    lab = arrays["cand_labels"].astype(np.int64)
    nobs = arrays["nobs"]
    dz = arrays["dz_m"]
    observed = nobs > 0
    conf = np.where(observed, 0.0, np.nan).astype(np.float32)
    table = conf_by_label.get(t.index)
    if table is not None:
        keys, vals = table
        pos = np.searchsorted(keys, lab)
        pos = np.clip(pos, 0, max(keys.size - 1, 0))
        hit = (lab != 0) & (keys.size > 0) & (keys[pos] == lab) if keys.size else np.zeros(lab.shape, bool)
        conf = np.where(hit & observed, vals[pos] if keys.size else 0.0, conf).astype(np.float32)
    change = np.where(
        observed, np.where(np.nan_to_num(conf) >= level0, np.sign(np.nan_to_num(dz)), 0), CHANGE_NODATA
    ).astype(np.int8)
    return {"confidence": conf, "change": change}


@dataclass
class TiledChangeResult:
    """What :func:`change_test_tiled` made (products and figures; per-cell arrays stay in the products)."""

    outputs: dict[str, Path]
    grid: AOIGrid
    comparisons: list[str]
    vertical_offsets_m: dict[str, float]
    min_region_cells: int
    significance: str
    exact: bool
    summary: dict[str, Any] = field(default_factory=dict)
    passes: int = 0
    tiles_resumed: int = 0


#: the bands of the change raster of a large grid, in file order
CHANGE_BANDS = ("dz_m", "dtilde", "score", "confidence", "cell_confidence", "dz_sigma_m")


def change_test_tiled(
    epoch_a: Sequence,
    epoch_b: Sequence,
    model: SelfConsistencyModel,
    out_dir,
    *,
    params: ChangeParams = ChangeParams(),
    tiling=None,
    footprints=None,
    method: str = "self-consistency",
    epoch_names: tuple[str, str] | None = None,
    region_confidence: float = 99.0,
    prefix: str = "sc",
    plots: bool = True,
    progress: Progress | None = None,
) -> TiledChangeResult:
    """:func:`geocd.consistency.change_test` + :func:`geocd.change.products.write_change_products`, tile by tile.

    Parameters
    ----------
    epoch_a, epoch_b : pair-DEM files (or :class:`Reconstruction`), all on one AOI grid; a DEM standing
        for an epoch as ``open_reconstruction(path, kind="dem", name="dem_a")[0]``
    model : the self-consistency model
    out_dir : output folder (products as ``geocd change``; ``out_dir/.geocd-work`` makes a killed run
        resumable)
    tiling : :class:`geocd.demdiff.tiled.TilingParams`
    footprints : optional building polygons (GeoDataFrame or file) attributed at ``region_confidence``
    """
    from ..tiling.params import TilingParams

    t0 = time.perf_counter()
    tiling = tiling or TilingParams()
    prog = ensure_progress(progress)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    recs_a, recs_b, grid = [], [], None
    for lst, src in ((recs_a, epoch_a), (recs_b, epoch_b)):
        for r in src:
            if isinstance(r, Reconstruction):
                rec, g = r, open_reconstruction(r.path, kind=r.kind, name=r.name)[1]
            else:
                rec, g = open_reconstruction(r)
            if grid is None:
                grid = g
            elif rec.kind == "pair" and not g.same_as(grid):
                raise GridError(f"pair-DEM {rec.name} is on another grid than the first; run stereo on one AOI grid")
            lst.append(rec)
    if not recs_a or not recs_b:
        raise ConfigError("each epoch needs at least one pair-DEM or a DEM")
    pairs = [r for r in recs_a + recs_b if r.kind == "pair"]
    if pairs:
        grid = open_reconstruction(pairs[0].path)[1]
    names = [r.name for r in recs_a + recs_b]
    if len(set(names)) != len(names):
        raise ConfigError(f"reconstructions must have distinct names, got {names}")
    # the transfer calibration is a whole-scene fit: gathered over every tile below, then given to each tile
    calibrate = params.calibration == "pair" or (
        params.calibration == "auto" and not model_learned_on(model, recs_a + recs_b)
    )
    params = replace(params, calibration="none")
    significance = params.significance
    if significance == "region" and not model.has_region_test:
        significance = "cell"
    H, W = grid.shape
    frac = min(1.0, tiling.sample_cells / float(H * W))
    fp = None
    if footprints is not None:
        from ..io.vector import read_footprints

        fp = footprints if hasattr(footprints, "geometry") else read_footprints(footprints, crs=grid.crs)
    ea = epoch_names[0] if epoch_names else (recs_a[0].epoch or "A")
    eb = epoch_names[1] if epoch_names else (recs_b[0].epoch or "B")
    tg = TileGrid(grid, (tiling.tile_size, tiling.tile_size), 0)
    if H * W > tiling.exact_grid_cells:  # its largest product is assembled last: refuse now, not after the tiles
        check_assembly_room(
            RasterProduct(str(out / f"{prefix}_change.tif"), CHANGE_BANDS),
            grid.shape,
            out / WORK_DIR,
            out / f"{prefix}_change.tif",
        )
    passes = resumed = 0
    with open_engine(tiling.scheduler, n_workers=tiling.n_workers, memory_limit=tiling.memory_limit) as eng:

        def run(func, stage, params_, overlap, inputs=None, products=None, f=(0.0, 1.0)):
            nonlocal passes, resumed
            passes += 1
            r = run_tiled(
                func,
                tg.with_overlap(overlap),
                inputs or {},
                params=params_,
                out=out,
                stage=f"change-{passes:02d}-{stage}",
                key=None,
                products=products,
                scheduler=eng,
                progress=sub_progress(prog, f[0], f[1], f"{stage}: "),
            )
            resumed += r.n_resumed
            return r

        # 1. vertical offsets, a whole-scene median over every pair of reconstructions
        offsets = {n: 0.0 for n in names}
        job0 = _Job(grid, tuple(recs_a), tuple(recs_b), model, params, {}, frac, significance, fp is not None)
        if params.align != "none" and len(names) > 1:
            r = run(_t_offsets, "offsets", job0, 0, f=(0.0, 0.2))
            parts = [s for _, s in r.smalls()]
            idx = np.concatenate([s["idx"] for s in parts])
            order = np.argsort(idx, kind="stable")
            cells = []
            for rec in recs_a + recs_b:
                z = np.concatenate([s[f"{rec.name}|z"] for s in parts])[order]
                if rec.kind == "dem":
                    cells.append(DEMAsEpoch(z, None, rec.name))
                else:
                    cells.append(
                        _Cells(
                            rec.name,
                            z,
                            np.concatenate([s[f"{rec.name}|s"] for s in parts])[order],
                            np.concatenate([s[f"{rec.name}|v"] for s in parts])[order],
                        )
                    )
            offsets = vertical_offsets(cells, mode=params.align)
        job = _Job(grid, tuple(recs_a), tuple(recs_b), model, params, offsets, frac, significance, fp is not None)
        calibration = None
        if calibrate:
            # 1b. the transfer calibration, fitted to every comparison's cells (one cell of overlap: the slope)
            r = run(_t_calibration, "calibration", job, 1, f=(0.2, 0.3))
            parts = [s for _, s in r.smalls()]
            n_comp = len(recs_a) * len(recs_b)
            cols = {k: [] for k in ("dt", "sc", "slope", "mpu")}
            for c in range(n_comp):
                order = np.argsort(np.concatenate([s[f"{c}|idx"] for s in parts]), kind="stable")
                for k in cols:
                    cols[k].append(np.concatenate([s[f"{c}|{k}"] for s in parts])[order])
            calibration = fit_pair_calibration(
                model, *(np.concatenate(cols[k]) for k in ("dt", "sc", "slope", "mpu")), fit_edge=True
            )
            job = replace(job, calibration=calibration)
        # 2. the test on every tile
        mmu0 = int(params.min_region_cells) if params.min_region_cells is not None else 1
        probe = [rec.read(grid, (0, 0, 1, 1)) for rec in recs_a + recs_b]
        from ..consistency import window_cells

        mmu = (
            mmu0
            if params.min_region_cells is not None
            else (
                int(model.region_null.get("min_region_cells", 1)) if significance == "region" else window_cells(probe)
            )
        )
        ov = max(mmu - 1, 0) if significance == "cell" else 0
        if calibration is not None:
            ov = max(ov, 1)  # the slope of a tile's border cells needs their neighbours
        rc = run(_t_change, "test", job, ov, f=(0.2, 0.75))
        sm = [s for _, s in rc.smalls()]
        store = rc.store
        comparisons = sm[0]["comparisons"] if sm else []
        levels = sorted(params.confidences)
        conf_store = store
        if significance == "region":
            from ..tiling.regions import merge_regions

            merged = merge_regions([s["cand"] for s in sm], tg, mmu)
            rconf = model.region_confidence(merged.sum) if len(merged) else np.zeros(0)
            by_tile: dict = {}
            for k in range(len(merged)):
                for ti, sgn, lab in merged.members[k]:
                    by_tile.setdefault(ti, []).append((sgn * lab, float(rconf[k])))
            table = {}
            for ti, v in by_tile.items():
                v = sorted(v)
                table[ti] = (np.array([x for x, _ in v], np.int64), np.array([c for _, c in v], np.float32))
            r2 = run(
                _t_region_conf,
                "regions",
                (table, levels[0]),
                0,
                inputs={
                    "cand_labels": store.source("cand_labels"),
                    "nobs": store.source("nobs"),
                    "dz_m": store.source("dz_m"),
                },
                f=(0.75, 0.85),
            )
            conf_store = r2.store
        prog(0.86, "products")
        res_meta = dict(
            grid=grid,
            confidences=tuple(levels),
            comparisons=comparisons,
            vertical_offsets_m=offsets,
            min_region_cells=mmu,
            significance=significance,
            calibration=calibration,
        )
        if H * W <= tiling.exact_grid_cells:
            outputs = _write_exact(
                store,
                conf_store,
                tg,
                res_meta,
                out,
                model=model,
                fp=fp,
                method=method,
                ea=ea,
                eb=eb,
                region_confidence=region_confidence,
                prefix=prefix,
                plots=plots,
            )
            exact = frac >= 1.0
        else:
            outputs = _write_large(
                store,
                conf_store,
                tg,
                res_meta,
                out,
                model=model,
                fp=fp,
                method=method,
                ea=ea,
                eb=eb,
                region_confidence=region_confidence,
                prefix=prefix,
                plots=plots,
                run=run,
            )
            exact = False
    if not tiling.keep_work:
        remove_work(out)
    prog(1.0, "done")
    res = TiledChangeResult(
        outputs, grid, comparisons, offsets, mmu, significance, exact, passes=passes, tiles_resumed=resumed
    )
    res.summary = {
        "wall_s": time.perf_counter() - t0,
        "sample_fraction": frac,
        "calibration": calibration.to_dict() if calibration is not None else "none",
    }
    return res


def _gathered_result(store, conf_store, tg: TileGrid, meta: dict, win=None) -> ChangeResult:
    """The test's result on ``win`` (row0, col0, rows, cols; default the whole grid) from the stored arrays."""
    g = tg.grid
    win = win or (0, 0, g.height, g.width)
    return ChangeResult(
        store.read("dz_m", win),
        store.read("dtilde", win),
        store.read("score", win),
        conf_store.read("confidence", win),
        conf_store.read("change", win),
        store.read("nobs", win),
        cell_confidence=store.read("cell_confidence", win),
        dz_sigma_m=store.read("dz_sigma_m", win),
        **meta,
    )


def _write_exact(
    store, conf_store, tg, meta, out, *, model, fp, method, ea, eb, region_confidence, prefix, plots
) -> dict:
    """Small grids: the whole result gathered, written by :func:`write_change_products`."""
    from .products import write_change_products

    res = _gathered_result(store, conf_store, tg, meta)
    g = tg.grid
    buildings = None
    surfaces = (None, None)  # the epochs' surfaces are kept with footprints only
    if fp is not None:
        from .dsm_buildings import building_layer

        win = (0, 0, g.height, g.width)
        surfaces = (store.read("z_a", win), store.read("z_b", win))
        buildings, _ = building_layer(
            fp,
            res,
            g,
            z_a=surfaces[0],
            z_b=surfaces[1],
            model=model,
            report_confidence=region_confidence,
            epoch_a=ea,
            epoch_b=eb,
        )
    return write_change_products(
        out,
        res,
        g,
        method=method,
        epoch_a=ea,
        epoch_b=eb,
        region_confidence=region_confidence,
        model=model,
        buildings=buildings,
        prefix=prefix,
        plots=plots,
        backdrop_a_m=surfaces[0],
        backdrop_m=surfaces[1],
    )


def _t_mask(arrays, ctx):
    """The change mask at the reported confidence and its regions (merged across seams afterwards)."""
    from ..tiling.regions import tile_regions

    level, mmu = ctx.params
    conf = arrays["confidence"]
    nobs = arrays["nobs"]
    dz = arrays["dz_m"]
    sig = arrays["dz_sigma_m"]
    c = np.nan_to_num(conf, nan=0.0)
    mask = np.where(c >= level, np.sign(np.nan_to_num(dz)), 0).astype(np.int8)
    mask[~(nobs > 0)] = CHANGE_NODATA
    sign = np.where(mask == CHANGE_NODATA, 0, mask).astype(np.int8)
    sg = np.asarray(sig, np.float64)
    fin = np.isfinite(sg)
    tr = tile_regions(sign, dz, ctx.tile, ctx.grid)
    # per-label Σσ² and count of finite σ (correlated_volume_sigma), from the label raster
    lab = tr.labels
    for s in tr.stats:
        li = np.where(lab * s > 0, np.abs(lab), 0).ravel()
        n = tr.stats[s]["n"].size + 1
        tr.stats[s]["sig2"] = np.bincount(li, weights=np.where(fin, sg * sg, 0.0).ravel(), minlength=n)[1:]
        tr.stats[s]["nsig"] = np.bincount(li, weights=fin.ravel().astype(np.float64), minlength=n)[1:]
    labels = tr.labels
    tr.labels = None
    return TileOutput(arrays={"mask": mask, "labels": labels}, small=tr)


def _write_large(
    store, conf_store, tg, meta, out, *, model, fp, method, ea, eb, region_confidence, prefix, plots, run
) -> dict:
    """Large grids: rasters tile by tile, regions of the mask merged across seams."""
    from ..io.vector import qml_for, write_gpkg
    from ..tiling.regions import merge_regions, region_mask_window, regions_layer
    from .products import _BAND_DESCRIPTIONS, _BAND_UNITS
    from .building_layer import buildings_qml
    from .styles import write_raster_style

    g = tg.grid
    tags = {
        "method": method,
        "epoch_a": ea,
        "epoch_b": eb,
        "confidences": ",".join(f"{c:g}" for c in meta["confidences"]),
        "comparisons": "; ".join(meta["comparisons"]),
        "significance": meta["significance"],
        "min_region_cells": str(meta["min_region_cells"]),
    }
    if meta.get("calibration") is not None:
        tags["model_calibration"] = json.dumps(meta["calibration"].to_dict())
    names = CHANGE_BANDS
    srcs = {n: (conf_store if n == "confidence" else store).source(n) for n in names}
    srcs["nobs"] = store.source("nobs")
    mmu = int(meta["min_region_cells"])
    products = {
        "change": RasterProduct(
            str(out / f"{prefix}_change.tif"),
            names,
            tags=tags,
            units=tuple(_BAND_UNITS[n] for n in names),
            band_tags=[{"long_name": _BAND_DESCRIPTIONS[n]} for n in names],
        ),
        "change_mask": RasterProduct(
            str(out / f"{prefix}_change_mask.tif"),
            ("mask",),
            dtype="int8",
            nodata=CHANGE_NODATA,
            descriptions=("change",),
            units=("class",),
            tags={**tags, "mask_confidence_pct": f"{region_confidence:g}"},
            band_tags=[
                {
                    "long_name": f"change at {region_confidence:g} %: +1 raised, -1 "
                    "lowered, 0 unchanged, -128 not observed"
                }
            ],
            overview_resampling="nearest",
        ),
    }

    rm = run(
        _t_mask,
        "mask",
        (region_confidence, mmu),
        0,
        inputs={k: srcs[k] for k in ("confidence", "nobs", "dz_m", "dz_sigma_m")},
        products={"change_mask": products["change_mask"]},
        f=(0.86, 0.9),
    )
    # the change raster straight from the test's (and the region pass's) tiles: no copy of six bands
    paths = {
        "change": write_product(store, products["change"], g, store.tile_grid, band_stores={"confidence": conf_store}),
        **rm.products,
    }
    write_raster_style(paths["change"], qml_for("confidence"))
    write_raster_style(paths["change_mask"], qml_for("change_mask"))
    merged = merge_regions([s for _, s in rm.smalls()], tg, mmu)
    cell = g.cell_area_m2
    nc = max(float(mmu), 1.0)

    def vol_sigma(k: int) -> float:  # geocd.change.regions.correlated_volume_sigma
        n = float(merged.extra["nsig"][k])
        if n == 0:
            return float("nan")
        return float(cell * math.sqrt(float(merged.extra["sig2"][k]) / n * n * min(n, nc)))

    def conf_of(k: int) -> float:  # the median confidence of the region's cells
        m, sl = region_mask_window(merged, k, lambda t: rm.store.tile_array(t, "labels"), tg)
        c = conf_store.read("confidence", (sl[0].start, sl[1].start, m.shape[0], m.shape[1]))[m]
        c = c[np.isfinite(c)]
        return float(np.median(c)) if c.size else float("nan")

    layer = regions_layer(
        merged, g, cell_area_m2=cell, method=method, epoch_a=ea, epoch_b=eb, volume_sigma=None, confidence=conf_of
    )
    if len(layer):
        layer["volume_sigma_m3"] = [vol_sigma(k) for k in range(len(merged))]
    layers: dict[str, Any] = {"changes": layer}
    styles = {"changes": qml_for("changes")}
    if fp is not None:
        layers["buildings"] = _buildings(fp, store, conf_store, tg, meta, model, region_confidence)
        styles["buildings"] = buildings_qml()
    if model is not None:
        layers["curves"] = model.curves_table()
    paths["changes"] = write_gpkg(out / f"{prefix}_changes.gpkg", layers, styles=styles)
    if plots and model is not None:
        from .plots import plot_scatter_curves

        paths["scatter"] = plot_scatter_curves(model, out / f"{prefix}_scatter.png")
    return paths


def _buildings(fp, store, conf_store, tg: TileGrid, meta: dict, model, level: float):
    """The building layer footprint by footprint (:func:`~geocd.change.dsm_buildings.classify_damage` on each
    footprint's window of the stored arrays). No whole-scene ground model here: heights and the ground-level
    tests use the median of a ring around each footprint, and no new building is searched outside them."""
    import geopandas as gpd
    import pandas as pd

    from .building_layer import empty_layer, footprint_id_field, footprints_with_ids, order_columns
    from .buildings import footprint_windows
    from .dsm_buildings import classify_damage

    g = tg.grid
    if not len(fp):
        return empty_layer(g.crs)
    gdf = footprints_with_ids(fp, g.crs, footprint_id_field(fp))
    rows = []
    for i, win, sub, near in footprint_windows(gdf, g):
        o = classify_damage(
            gdf.iloc[near],
            _gathered_result(store, conf_store, tg, {**meta, "grid": sub}, win),
            sub,
            z_a=store.read("z_a", win),
            z_b=store.read("z_b", win),
            model=model,
            report_confidence=level,
            id_field="building_id",
        )
        rows.append(o.iloc[int(np.nonzero(near == i)[0][0])].copy())
    out = gpd.GeoDataFrame(pd.DataFrame(rows).reset_index(drop=True), geometry="geometry", crs=gdf.crs)
    return order_columns(out)
