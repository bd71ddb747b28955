"""End-to-end generation of a synthetic scene folder (images, cameras, truth, manifest).

``generate(SynthParams(...), out_dir)`` writes::

    scene.yaml                      geocd manifest (epochs A and B, AOI, DEM prior, footprints, truth)
    images/A_sat1.tif ...           11-bit pushbroom views (uint16, NBITS=11) with RPC00B GeoTIFF tags
    images/A_air1.tif ...           RGB uint8 frame views (+ A_air1.camera.json frame sidecars)
    images/B_sat1.tif ...
    truth/dsm_A.tif, dsm_B.tif      exact DSMs (ellipsoidal heights, float32, AOI grid)
    truth/dem_bare.tif              terrain only; truth/dem_prior.tif: a smoothed 2 m prior (the manifest's DEM)
    truth/dsm_diff.tif              DSM_B − DSM_A
    truth/change_mask.tif           1 where |ΔDSM| > threshold (uint8); change_class.tif: 1 building 2 car 3 tree
    truth/non3d_mask.tif            1 repainted roof, 2 vegetation season (appearance change, no 3-D change)
    truth/cover_A.tif, cover_B.tif  surface cover seen from above: 1 grass 2 tree 3 building 4 car 5 asphalt
                                    6 pavement 7 soil 8 marking (vegetation = grass or tree)
    truth/footprints_A.gpkg, footprints_B.gpkg, footprints_all.gpkg   (status, building_id stable)
    truth/objects.gpkg              trees and cars per epoch
    truth/image_masks/<image>.tif   per-image 3-D change masks (image geometry): band 1 mask, band 2 % of samples
    truth/cameras/<image>.json      the physical camera of every view (pushbroom or frame)
    truth/scene_truth.json          parameters, sensors, sun, changes, RPC fit report, checks, timings

Deterministic: the same :class:`SynthParams` (seed included) give the same
pixels and truth (see :func:`generate` for the tolerance across machines).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import numbers
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Sequence
from typing import Any, Callable

import numpy as np

from ..errors import ConfigError
from ..io.outputs import LOCK_NAME, MANIFEST_NAME
from ..params import ParamsMixin
from ..progress import ensure_progress, sub_progress
from .scene import CHANGE_TYPES, Town, TownParams, build_town

#: satellite orbit heading (descending sun-synchronous pass)
HEADING_DEG = 192.0


@dataclass(frozen=True)
class SynthParams(ParamsMixin):
    """Everything that defines a synthetic scene folder (frozen; ``seed`` makes it reproducible).

    Attributes
    ----------
    seed : int
    size_m, margin_m : AOI side and scene margin around it (metres; margin None = auto)
    gsd_m : satellite ground sampling distance (m); posting_m: truth/AOI grid posting
    n_sat_a, n_sat_b : satellite views per epoch; n_aerial : aerial frames (epoch A)
    along_a_deg, across_a_deg, along_b_deg, across_b_deg : pitch range and roll of each epoch's pass
    date_a, date_b : acquisition times (UTC, ISO 8601); they set the sun
    same_sun : render epoch B under epoch A's sun (illumination-robustness control)
    aerial_gsd_m, aerial_height_m : frame camera GSD and flying height above the scene centre
    supersample : k × k rays per pixel
    changes : enabled change types (see :data:`geocd.synth.scene.CHANGE_TYPES`)
    n_new, n_demolished, n_raised, n_lowered, n_cars_moved, n_trees_changed, n_repainted
    n_buildings : buildings in the AOI in epoch A (None: 32 per 300 m × 300 m)
    change_threshold_m : |ΔDSM| threshold of the truth change mask
    rpc_n_xy, rpc_n_h : RPC fit grid
    """

    seed: int = 0
    size_m: float = 300.0
    margin_m: float | None = None
    gsd_m: float = 0.5
    posting_m: float = 0.5
    center_lon: float = 1.4440
    center_lat: float = 43.5620
    base_height_m: float = 196.0
    n_sat_a: int = 4
    n_sat_b: int = 3
    n_aerial: int = 3
    along_a_deg: tuple[float, float] = (-22.0, 20.0)
    across_a_deg: float = 7.0
    along_b_deg: tuple[float, float] = (-16.0, 14.0)
    across_b_deg: float = -12.0
    altitude_m: float = 620e3
    date_a: str = "2023-07-18T10:40:00"
    date_b: str = "2024-03-26T11:05:00"
    same_sun: bool = False
    aerial_gsd_m: float = 0.3
    aerial_height_m: float = 700.0
    supersample: int = 2
    changes: tuple[str, ...] = CHANGE_TYPES
    n_buildings: int | None = None
    n_new: int = 3
    n_demolished: int = 2
    n_raised: int = 2
    n_lowered: int = 1
    n_cars_moved: int = 4
    n_trees_changed: int = 2
    n_repainted: int = 2
    change_threshold_m: float = 1.0
    rpc_n_xy: int = 21
    rpc_n_h: int = 9
    name: str = "sample_aoi"

    def __post_init__(self) -> None:
        if self.n_sat_a < 0 or self.n_sat_b < 0 or self.n_aerial < 0:
            raise ConfigError("numbers of views must be ≥ 0")
        if self.n_sat_a + self.n_aerial < 1 or self.n_sat_b < 1:
            raise ConfigError("each epoch needs at least one image (n_sat_a + n_aerial ≥ 1, n_sat_b ≥ 1)")
        if not (0.05 <= self.gsd_m <= 10 and 0.05 <= self.posting_m <= 10 and 0.02 <= self.aerial_gsd_m <= 2):
            raise ConfigError(
                f"GSD/posting out of range: gsd_m={self.gsd_m}, posting_m={self.posting_m}, "
                f"aerial_gsd_m={self.aerial_gsd_m}"
            )
        for v in (*self.along_a_deg, *self.along_b_deg, self.across_a_deg, self.across_b_deg):
            if abs(v) > 45:
                raise ConfigError(f"view angles must be within ±45°, got {v}")
        for d in (self.date_a, self.date_b):
            try:
                _dt.datetime.fromisoformat(d)
            except ValueError as exc:
                raise ConfigError(f"date {d!r} is not ISO 8601 (YYYY-MM-DDTHH:MM:SS, UTC)") from exc
        TownParams(size_m=self.size_m, changes=tuple(self.changes))  # validates size and change names
        k = self.supersample  # checked here, before anything is rendered (RenderParams checks it late)
        if isinstance(k, bool) or not isinstance(k, numbers.Integral) or not 1 <= k <= 8:
            raise ConfigError(f"supersample must be a whole number within 1..8 (k × k rays per pixel), got {k!r}")

    @property
    def margin(self) -> float:
        return self.margin_m if self.margin_m is not None else float(min(40.0, max(12.0, self.size_m / 4.0)))

    def town_params(self) -> TownParams:
        return TownParams(
            seed=self.seed,
            size_m=self.size_m,
            margin_m=self.margin,
            center_lon=self.center_lon,
            center_lat=self.center_lat,
            base_height_m=self.base_height_m,
            n_buildings=self.n_buildings,
            n_new=self.n_new,
            n_demolished=self.n_demolished,
            n_raised=self.n_raised,
            n_lowered=self.n_lowered,
            n_cars_moved=self.n_cars_moved,
            n_trees_changed=self.n_trees_changed,
            n_repainted=self.n_repainted,
            season="season" in self.changes,
            changes=tuple(self.changes),
        )

    _kind = "synth"  # names the parameter set in ConfigError messages

    @classmethod
    def tiny(cls, **kw: Any) -> "SynthParams":
        """A 64 m × 64 m scene with 2+2 satellite views and 2 aerial frames (for tests)."""
        base = dict(
            size_m=64.0,
            n_sat_a=2,
            n_sat_b=2,
            n_aerial=2,
            n_buildings=4,
            n_new=1,
            n_demolished=1,
            n_raised=1,
            n_lowered=0,
            n_cars_moved=1,
            n_trees_changed=1,
            n_repainted=1,
            name="tiny",
        )
        base.update(kw)
        return cls(**base)


@dataclass
class SynthResult:
    """What :func:`generate` wrote and measured."""

    out_dir: Path
    manifest: Path
    report: dict = field(default_factory=dict)


def _views(p: SynthParams) -> list[dict]:
    """Satellite view list: name, epoch, along, across."""
    out = []
    for ep, n, (a0, a1), ac in (
        ("A", p.n_sat_a, p.along_a_deg, p.across_a_deg),
        ("B", p.n_sat_b, p.along_b_deg, p.across_b_deg),
    ):
        alongs = [0.5 * (a0 + a1)] if n == 1 else list(np.linspace(a0, a1, n))
        for i, a in enumerate(alongs):
            out.append({"name": f"{ep}_sat{i + 1}", "epoch": ep, "along_deg": round(float(a), 4), "across_deg": ac})
    return out


def _sun(p: SynthParams, town: Town) -> dict:
    from .sensors import Sun, sun_position

    fr = town.frame
    sa = sun_position(fr.lon0, fr.lat0, _dt.datetime.fromisoformat(p.date_a))
    sb = sun_position(fr.lon0, fr.lat0, _dt.datetime.fromisoformat(p.date_b))
    if p.same_sun:
        sb = sa
    return {"A": Sun(sa[0], sa[1], p.date_a), "B": Sun(sb[0], sb[1], p.date_b + (" (sun of A)" if p.same_sun else ""))}


def _cover_points(town: Town, pad_m: float = 0.0) -> np.ndarray:
    """AOI corners (and edge midpoints) at the lowest and highest scene heights, lon/lat/h."""
    x0, y0, x1, y1 = town.aoi
    lo, hi = town.aoi_height_range()
    pts = []
    for x in (x0 - pad_m, 0.5 * (x0 + x1), x1 + pad_m):
        for y in (y0 - pad_m, 0.5 * (y0 + y1), y1 + pad_m):
            for z in (lo - 2.0, hi + 2.0):
                lon, lat = town.frame.to_lonlat(x, y)
                pts.append([float(lon), float(lat), z])
    return np.array(pts)


def make_satellite_cameras(p: SynthParams, town: Town) -> dict:
    """Physical pushbroom cameras of all satellite views (name → camera)."""
    from .sensors import make_pushbroom

    fr = town.frame
    cover = _cover_points(town)
    cams = {}
    for v in _views(p):
        cams[v["name"]] = make_pushbroom(
            fr.lon0,
            fr.lat0,
            fr.h0,
            along_deg=v["along_deg"],
            across_deg=v["across_deg"],
            heading_deg=HEADING_DEG,
            altitude_m=p.altitude_m,
            gsd_m=p.gsd_m,
            cover_lonlath=cover,
            margin_px=8,
            name=v["name"],
        )
    return cams


def make_aerial_cameras(p: SynthParams, town: Town) -> dict:
    """Frame cameras of the aerial strip (epoch A): an east–west line, 60% forward overlap, slight tilts."""
    from ..camera.frame import FrameCamera

    if p.n_aerial == 0:
        return {}
    fr = town.frame
    rng = np.random.default_rng(np.random.SeedSequence([p.seed, 0xA1]))
    lo, hi = town.aoi_height_range()
    ground = float(town.terrain.at(0.0, 0.0))
    n = p.n_aerial
    cover_x = p.size_m + 16.0
    cover_y = p.size_m + 16.0
    overlap = 0.6
    wg = cover_x / (1.0 + (n - 1) * (1.0 - overlap))
    step = wg * (1.0 - overlap)
    f_px = p.aerial_height_m / p.aerial_gsd_m
    # the image must also hold the parallax of the tallest objects near its edges
    w_px = int(math.ceil(wg / p.aerial_gsd_m / 2.0)) * 2 + 16
    h_px = int(math.ceil(cover_y / p.aerial_gsd_m / 2.0)) * 2 + 16
    cams = {}
    for i in range(n):
        x = -0.5 * (n - 1) * step + i * step
        omega, phi = rng.normal(0.0, 1.0, 2)
        kappa = rng.normal(0.0, 0.5)
        pos = (fr.e0 + x, fr.n0 + rng.normal(0.0, 2.0), ground + p.aerial_height_m)
        cams[f"A_air{i + 1}"] = FrameCamera(
            width=w_px,
            height=h_px,
            focal_px=f_px,
            position=pos,
            opk_deg=(float(omega), float(phi), float(kappa)),
            crs=fr.crs,
            vertical_datum="ellipsoid",
            source=f"geocd synth aerial frame {i + 1}",
        )
    return cams


def _sat_radiometry(p: SynthParams, rng: np.random.Generator, off_nadir: float):
    from .render import SensorRadiometry

    return SensorRadiometry(
        nbits=11,
        gain=float(1500.0 * rng.uniform(0.94, 1.06)),
        dark=float(rng.uniform(30, 50)),
        haze=float(0.015 + 0.02 * (off_nadir / 30.0) + rng.uniform(0, 0.01)),
        psf_sigma_px=0.5,
        electrons_per_count=8.0,
        read_noise=2.0,
        bands="pan",
    )


def _aerial_radiometry(rng: np.random.Generator):
    from .render import SensorRadiometry

    return SensorRadiometry(
        nbits=8,
        gain=float(215.0 * rng.uniform(0.97, 1.03)),
        dark=4.0,
        haze=0.01,
        psf_sigma_px=0.4,
        electrons_per_count=25.0,
        read_noise=0.8,
        gamma=2.2,
        bands="rgb",
    )


def _write_truth_raster(path: Path, arr: np.ndarray, grid, *, dtype: str, nodata=None, tags=None, names=None) -> None:
    from ..io.raster import write_cog

    bands = {n: a for n, a in zip(names, arr)} if names else arr
    write_cog(path, bands, grid, dtype=dtype, nodata=nodata, tags=tags or {})


def _prior_dem(bare: np.ndarray, grid, factor: int = 4):
    """A smoothed, coarser terrain model (what a user has before the survey: SRTM-like, here 2 m)."""
    from scipy.ndimage import gaussian_filter

    from ..geodesy import AOIGrid
    from affine import Affine

    sm = gaussian_filter(bare, 8.0, mode="nearest")
    h, w = sm.shape
    hc, wc = h // factor, w // factor
    coarse = sm[: hc * factor, : wc * factor].reshape(hc, factor, wc, factor).mean(axis=(1, 3))
    t = grid.transform
    g2 = AOIGrid(grid.crs, Affine(t.a * factor, 0, t.c, 0, t.e * factor, t.f), wc, hc)
    return coarse.astype(np.float32), g2


def generate(
    params: SynthParams,
    out_dir: os.PathLike | str,
    *,
    overwrite: bool = False,
    progress: Callable | None = None,
    only_views: Sequence[str] | None = None,
    mask_views: Sequence[str] | None = None,
) -> SynthResult:
    """Build the town, render every view, fit and write RPCs, write truth and the manifest.

    Parameters
    ----------
    params : SynthParams
    out_dir : folder to write (created; must be empty unless ``overwrite``)
    overwrite : replace the files of an existing scene folder
    only_views : render and write only these views (names such as ``"B_sat1"``; default: every view). Each one
        is the image a full run writes, pixel for pixel: the other views' cameras and noise streams are still
        drawn. For tests and benchmarks that need a few views of a large town.
    mask_views : write the per-image change masks (``truth/image_masks``) of only these views (default: every
        written view). A mask traces every pixel's rays into both epochs (about half the time of rendering the
        view); an evaluation that scores only some views (the epoch-B ones) needs only theirs.

    Returns
    -------
    SynthResult with the manifest path and a report (RPC fit residuals, corner checks, timings).

    Notes
    -----
    Reproducibility: every random draw comes from generators seeded by
    ``params.seed``; the ray casting is deterministic. On the same machine and
    library versions the written pixels and truth are identical bit for bit;
    across CPUs or numba/numpy versions floating-point differences may change
    rare pixels by ±1 count (documented tolerance: ≤ 1 count on ≤ 0.1% of the
    pixels, truth rasters equal to 1e-6 m).
    """
    from ..camera.rpc_fit import _single_thread_blas

    with _single_thread_blas():  # numba does the parallel work; BLAS threads would only contend with it
        return _generate(
            params, out_dir, overwrite=overwrite, progress=progress, only_views=only_views, mask_views=mask_views
        )


def _generate(
    params: SynthParams,
    out_dir: os.PathLike | str,
    *,
    overwrite: bool = False,
    progress: Callable | None = None,
    only_views: Sequence[str] | None = None,
    mask_views: Sequence[str] | None = None,
) -> SynthResult:
    from ..camera.rpc_fit import fit_rpc
    from ..errors import OutputError
    from ..io.atomic import write_text_atomic
    from ..io.raster import write_image
    from ..io.vector import write_gpkg
    from .render import RenderParams, pack_scene, render_view, to_sensor_counts
    from .truth import (
        bare_dem,
        change_products,
        corner_check,
        dsm,
        footprints_all,
        footprints_frame,
        image_change_mask,
        non3d_mask,
        objects_frame,
        truth_grid,
        write_cover_truth,
    )

    prog = ensure_progress(progress)
    out = Path(out_dir)
    # geocd's own bookkeeping of the output session (lock, product manifest) does not make the folder a scene
    bookkeeping = {LOCK_NAME, MANIFEST_NAME}
    if out.exists() and any(p.name not in bookkeeping for p in out.iterdir()) and not overwrite:
        raise OutputError(f"{out} is not empty; choose a new folder or pass overwrite=True (--overwrite)")
    out.mkdir(parents=True, exist_ok=True)
    (out / "images").mkdir(exist_ok=True)
    (out / "truth" / "image_masks").mkdir(parents=True, exist_ok=True)
    (out / "truth" / "cameras").mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    timings: dict[str, float] = {}
    report: dict[str, Any] = {"params": params.to_dict()}

    # --- scene ------------------------------------------------------------------------------
    t0 = time.perf_counter()
    town = build_town(params.town_params())
    scenes = {"A": pack_scene(town, "A"), "B": pack_scene(town, "B")}
    suns = _sun(params, town)
    timings["scene_s"] = time.perf_counter() - t0
    prog(0.02, "scene built")

    # --- truth rasters ------------------------------------------------------------------------------
    t0 = time.perf_counter()
    grid = truth_grid(town, params.posting_m)
    dsm_a, cls_a = dsm(town, scenes["A"], grid)
    dsm_b, cls_b = dsm(town, scenes["B"], grid)
    bare = bare_dem(town, grid)
    mask, ccls, sign = change_products(dsm_a, dsm_b, cls_a, cls_b, params.posting_m, params.change_threshold_m)
    n3d = non3d_mask(town, scenes["A"], scenes["B"], grid, mask)
    ell = {"vertical_datum": "ellipsoid", "units": "metre", "heights": "WGS84 ellipsoidal"}
    tdir = out / "truth"
    _write_truth_raster(
        tdir / "dsm_A.tif",
        dsm_a.astype(np.float32),
        grid,
        dtype="float32",
        tags={**ell, "content": "truth DSM epoch A (first surface from above at cell centres)"},
    )
    _write_truth_raster(
        tdir / "dsm_B.tif",
        dsm_b.astype(np.float32),
        grid,
        dtype="float32",
        tags={**ell, "content": "truth DSM epoch B"},
    )
    _write_truth_raster(
        tdir / "dem_bare.tif",
        bare.astype(np.float32),
        grid,
        dtype="float32",
        tags={**ell, "content": "bare-earth terrain (truth)"},
    )
    prior, g2 = _prior_dem(bare, grid)
    _write_truth_raster(
        tdir / "dem_prior.tif",
        prior,
        g2,
        dtype="float32",
        tags={**ell, "content": "smoothed 2 m terrain prior (Gaussian 4 m, block mean), no buildings"},
    )
    _write_truth_raster(
        tdir / "dsm_diff.tif",
        (dsm_b - dsm_a).astype(np.float32),
        grid,
        dtype="float32",
        tags={"units": "metre", "content": "DSM_B - DSM_A"},
    )
    thr_doc = (
        f"1 where |DSM_B - DSM_A| > {params.change_threshold_m} m on exact (noise-free) DSMs sampled at cell "
        f"centres; connected regions < 1 m2 removed; 0 elsewhere"
    )
    _write_truth_raster(
        tdir / "change_mask.tif",
        mask,
        grid,
        dtype="uint8",
        tags={"content": thr_doc, "threshold_m": params.change_threshold_m},
    )
    _write_truth_raster(
        tdir / "change_class.tif",
        ccls,
        grid,
        dtype="uint8",
        tags={"content": "class of the changed object: 0 none, 1 building, 2 car, 3 tree"},
    )
    _write_truth_raster(
        tdir / "change_sign.tif", sign, grid, dtype="int8", tags={"content": "+1 raised, -1 lowered, 0 no 3-D change"}
    )
    _write_truth_raster(
        tdir / "non3d_mask.tif",
        n3d,
        grid,
        dtype="uint8",
        tags={"content": "appearance change without 3-D change: 1 repainted roof, 2 vegetation season"},
    )
    write_cover_truth(tdir, town, scenes, grid)
    write_gpkg(tdir / "footprints_A.gpkg", {"footprints": footprints_frame(town, "A")})
    write_gpkg(tdir / "footprints_B.gpkg", {"footprints": footprints_frame(town, "B")})
    write_gpkg(tdir / "footprints_all.gpkg", {"footprints": footprints_all(town)})
    write_gpkg(
        tdir / "objects.gpkg",
        {
            "trees_A": objects_frame(town, "A", "trees"),
            "trees_B": objects_frame(town, "B", "trees"),
            "cars_A": objects_frame(town, "A", "cars"),
            "cars_B": objects_frame(town, "B", "cars"),
        },
    )
    timings["truth_rasters_s"] = time.perf_counter() - t0
    prog(0.06, "truth rasters written")

    # --- cameras --------------------------------------------------------------------------------------
    sat = make_satellite_cameras(params, town)
    air = make_aerial_cameras(params, town)
    views = []
    for v in _views(params):
        views.append({**v, "kind": "satellite", "camera": sat[v["name"]]})
    for name, cam in air.items():
        views.append({"name": name, "epoch": "A", "kind": "aerial", "camera": cam})
    order = {"A": 0, "B": 1}
    views.sort(key=lambda v: (order[v["epoch"]], v["kind"] != "satellite", v["name"]))
    for arg, names in (("only_views", only_views), ("mask_views", mask_views)):
        unknown = sorted(set(names or ()) - {v["name"] for v in views})
        if unknown:
            raise ConfigError(
                f"{arg} names no view of this scene: {unknown}; its views are {[v['name'] for v in views]}"
            )

    h_lo, h_hi = town.aoi_height_range()
    rpc_h = (math.floor(h_lo - 10.0), math.ceil(h_hi + 15.0))
    rparams = RenderParams(supersample=params.supersample)
    view_reports = []
    nv = len(views)
    for iv, v in enumerate(views):  # iv seeds the view's noise: the same with or without only_views
        name, cam, ep = v["name"], v["camera"], v["epoch"]
        if only_views is not None and name not in only_views:
            continue
        vp = sub_progress(prog, 0.08 + 0.9 * iv / nv, 0.08 + 0.9 * (iv + 1) / nv, f"{name}: ")
        rng = np.random.default_rng(np.random.SeedSequence([params.seed, order[ep], iv, 77]))
        vr: dict[str, Any] = {
            "name": name,
            "epoch": ep,
            "kind": v["kind"],
            "width": cam.width,
            "height": cam.height,
            "sun": suns[ep].to_dict(),
        }
        t0 = time.perf_counter()
        res = render_view(
            town, ep, cam, suns[ep].direction_enu(), rparams, scene=scenes[ep], progress=sub_progress(vp, 0.0, 0.7)
        )
        vr["render_s"] = round(time.perf_counter() - t0, 3)
        vr["pixels_per_s"] = round(cam.width * cam.height / max(res.seconds, 1e-9), 1)
        img_path = out / "images" / f"{name}.tif"
        acq = params.date_a if ep == "A" else params.date_b
        tags = {
            "GEOCD_SYNTH": f"seed={params.seed}",
            "ACQUISITION_DATETIME": acq,
            "SUN_AZIMUTH": f"{suns[ep].azimuth_deg:.4f}",
            "SUN_ELEVATION": f"{suns[ep].elevation_deg:.4f}",
        }
        if v["kind"] == "satellite":
            info = cam.info
            vr.update(
                {
                    k: info[k]
                    for k in (
                        "along_deg",
                        "across_deg",
                        "off_nadir_deg",
                        "incidence_deg",
                        "view_azimuth_deg",
                        "slant_range_m",
                    )
                }
            )
            radio = _sat_radiometry(params, rng, float(info["off_nadir_deg"]))
            counts = to_sensor_counts(res.radiance, radio, rng)
            t0 = time.perf_counter()
            rpc, fit = fit_rpc(
                cam,
                rpc_h,
                n_xy=params.rpc_n_xy,
                n_h=params.rpc_n_h,
                source=f"geocd synth: RPC00B fitted to the physical pushbroom model of {name}",
            )
            vr["rpc_fit_s"] = round(time.perf_counter() - t0, 3)
            vr["rpc_fit"] = fit.to_dict()
            vr["rpc_vs_physical_aoi"] = _aoi_difference(town, cam, rpc, (h_lo, h_hi))
            tags.update(
                {
                    "SATELLITE_VIEW_OFF_NADIR": f"{info['off_nadir_deg']:.4f}",
                    "SATELLITE_VIEW_AZIMUTH": f"{info['view_azimuth_deg']:.4f}",
                }
            )
            write_image(img_path, counts, rpc=rpc, nbits=11, tags=tags)
            geo_model = rpc
        else:
            from ..io.frame import write_frame_sidecar

            radio = _aerial_radiometry(rng)
            counts = to_sensor_counts(res.radiance, radio, rng)
            write_image(img_path, counts, tags=tags, photometric="RGB")
            write_frame_sidecar(img_path, cam)
            geo_model = cam
        vr["radiometry"] = radio.to_dict()
        (tdir / "cameras" / f"{name}.json").write_text(json.dumps(cam.to_dict(), indent=1), encoding="utf-8")
        if mask_views is None or name in mask_views:
            vp(0.8, "truth mask")
            m, frac = image_change_mask(
                town,
                cam,
                scenes["A"],
                scenes["B"],
                threshold_m=params.change_threshold_m,
                supersample=params.supersample,
            )
            write_image(
                tdir / "image_masks" / f"{name}.tif",
                np.stack([m, np.rint(frac * 100).astype(np.uint8)]),
                tags={
                    "content": f"band 1: 1 where the pixel sees a 3-D change (surfaces > "
                    f"{params.change_threshold_m} m apart between epochs for >= half of its "
                    f"{params.supersample**2} samples); band 2: percent of such samples"
                },
            )
            vr["changed_pixel_fraction"] = round(float(m.mean()), 5)
        vr["corner_check"] = corner_check(town, ep, scenes[ep], cam, geo_model)
        view_reports.append(vr)
        vp(1.0, "done")

    # --- manifest and report ---------------------------------------------------------------------------------
    report["frame"] = town.frame.to_dict()
    report["crs"] = f"EPSG:{town.frame.epsg}"
    report["aoi_bounds"] = [float(b) for b in grid.bounds]
    report["aoi_height_range_m"] = [h_lo, h_hi]
    report["rpc_height_range_m"] = list(rpc_h)
    report["sun"] = {k: s.to_dict() for k, s in suns.items()}
    report["changes"] = [c.to_dict() for c in town.changes]
    report["change_threshold_m"] = params.change_threshold_m
    report["change_mask_fraction"] = round(float(mask.mean()), 5)
    report["n_buildings"] = {k: len(e.buildings) for k, e in town.epochs.items()}
    report["views"] = view_reports
    timings["total_s"] = time.perf_counter() - t_all
    report["timings"] = {k: round(v, 3) for k, v in timings.items()}
    report["software"] = _versions()
    write_text_atomic(tdir / "scene_truth.json", json.dumps(report, indent=1, default=_json_default))
    if only_views is not None:
        views = [v for v in views if v["name"] in only_views]
    masked = [v["name"] for v in views if mask_views is None or v["name"] in mask_views]
    manifest = _write_manifest(out, params, town, grid, views, masked)
    prog(1.0, "done")
    return SynthResult(out, manifest, report)


def _aoi_difference(town: Town, cam, rpc, h_range: tuple[float, float], n: int = 41, nh: int = 11) -> dict:
    """Physical model vs fitted RPC over the AOI and its height range (pixels)."""
    x0, y0, x1, y1 = town.aoi
    X, Y, Z = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n), np.linspace(h_range[0], h_range[1], nh))
    lon, lat = town.frame.to_lonlat(X.ravel(), Y.ravel())
    c1, r1 = cam.project(lon, lat, Z.ravel())
    c2, r2 = rpc.project(lon, lat, Z.ravel())
    e = np.hypot(c1 - c2, r1 - r2)
    return {
        "max_px": float(e.max()),
        "rms_px": float(np.sqrt(np.mean(e**2))),
        "n_points": int(e.size),
        "h_range_m": [float(h_range[0]), float(h_range[1])],
    }


def _write_manifest(out: Path, p: SynthParams, town: Town, grid, views: list[dict], masked: list[str]) -> Path:
    import yaml

    from ..io.atomic import write_text_atomic

    def imgs(ep: str) -> list[dict]:
        res = []
        for v in views:
            if v["epoch"] != ep:
                continue
            d = {"path": f"images/{v['name']}.tif", "name": v["name"]}
            if v["kind"] == "aerial":
                d["camera"] = f"images/{v['name']}.camera.json"
            res.append(d)
        return res

    sens_b = f"pushbroom-sim {p.gsd_m:g} m pan 11-bit"
    sens_a = sens_b + (f" + frame-sim {p.aerial_gsd_m:g} m RGB" if p.n_aerial else "")
    truth = {
        "dsm_A": "truth/dsm_A.tif",
        "dsm_B": "truth/dsm_B.tif",
        "dem_bare": "truth/dem_bare.tif",
        "dem_prior": "truth/dem_prior.tif",
        "dsm_diff": "truth/dsm_diff.tif",
        "footprints_A": "truth/footprints_A.gpkg",
        "footprints_B": "truth/footprints_B.gpkg",
        "footprints_all": "truth/footprints_all.gpkg",
        "objects": "truth/objects.gpkg",
        "change_mask": "truth/change_mask.tif",
        "change_class": "truth/change_class.tif",
        "change_sign": "truth/change_sign.tif",
        "non3d_mask": "truth/non3d_mask.tif",
        "change_threshold_m": p.change_threshold_m,
        "image_masks": {name: f"truth/image_masks/{name}.tif" for name in masked},
        "cameras": {v["name"]: f"truth/cameras/{v['name']}.json" for v in views},
        "report": "truth/scene_truth.json",
        "satellite_images": [v["name"] for v in views if v["kind"] == "satellite"],
        "aerial_images": [v["name"] for v in views if v["kind"] == "aerial"],
        "same_sun": bool(p.same_sun),
    }
    doc = {
        "geocd_manifest": 1,
        "name": p.name,
        "description": (
            f"geocd synthetic town (seed {p.seed}): {p.size_m:g} m x {p.size_m:g} m, two epochs with known "
            "3-D changes (new, demolished, raised, lowered buildings, cars, trees) and non-3-D changes "
            "(repainted roofs, season, sun). Regenerate with: geocd synth --out DIR --seed "
            f"{p.seed}" + (" (see truth/scene_truth.json for all parameters)")
        ),
        "scene_class": "suburban",
        "aoi": {"crs": f"EPSG:{town.frame.epsg}", "bounds": [float(b) for b in grid.bounds], "posting_m": p.posting_m},
        "dem": {"path": "truth/dem_prior.tif", "vertical_datum": "ellipsoid"},
        # the buildings of the earlier date only (what a user has at best): new ones must come from detection
        "footprints": "truth/footprints_A.gpkg",
        # the simulated cameras are exact: no cross-epoch bias to estimate
        "orientation": False,
        "epochs": [
            {"name": "A", "date": p.date_a[:10], "sensor": sens_a, "images": imgs("A")},
            {"name": "B", "date": p.date_b[:10], "sensor": sens_b, "images": imgs("B")},
        ],
        "truth": truth,
    }
    path = out / "scene.yaml"
    write_text_atomic(path, yaml.safe_dump(doc, sort_keys=False, width=120, allow_unicode=True))
    return path


def _versions() -> dict:
    import numba
    import rasterio

    return {
        "numpy": np.__version__,
        "numba": numba.__version__,
        "rasterio": rasterio.__version__,
        "gdal": rasterio.__gdal_version__,
    }


def _json_default(o):
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
