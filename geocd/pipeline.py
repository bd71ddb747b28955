"""The full run: stereo → self-consistency baseline → change test → products.

One config tree (:class:`RunConfig`, frozen dataclasses) drives it and is
written beside the outputs (``run_config.json``) as a record of the run,
together with ``run_summary.json`` (inputs, grid, counts, outputs).

Epoch roles: the first and last epochs of the manifest (by date, else by
order) are compared; every epoch with two or more pair-DEMs contributes its
within-epoch comparisons to the baseline (unless a scene-class model is given).
An epoch given as a DEM (``epochs[].dem``, no images) stands for that epoch
(:class:`geocd.consistency.DEMAsEpoch`).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
import os
import time
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .change.buildings import BuildingParams
from .consistency import (
    ChangeParams,
    ConsistencyParams,
    DEMAsEpoch,
    SelfConsistencyModel,
    change_test,
    learn_self_consistency,
)
from .errors import ConfigError, GeoCDError
from .io.atomic import write_text_atomic
from .io.manifest import pick_epochs
from .progress import Progress, ensure_progress, sub_progress
from .runlog import LoggedProgress, RunLog, log_file_name, logger
from .stereo.params import change_stereo_params
from .stereo.surface import epoch_surface


#: what ``geocd run`` writes into its output folder (globs, relative to it): see geocd.io.outputs.open_outputs
PRODUCTS = ("sc_*", "stereo/*", "screen/*", "self_consistency_model.json", "run_config.json", "run_summary.json")


@dataclass(frozen=True)
class RunConfig:
    """Every parameter of ``geocd run`` (written to ``run_config.json``).

    Attributes
    ----------
    stereo : StereoParams
        As :class:`geocd.stereo.StereoParams` except ``surface_median`` = 1 (off) unless given
        (:data:`geocd.stereo.params.RUN_STEREO_DEFAULTS`).
    consistency : ConsistencyParams
    change : ChangeParams
    buildings : BuildingParams
    region_confidence : float
        Confidence (percent) at which changed regions/buildings are reported.
    model_path : str, optional
        A saved scene-class model to use instead of learning one (needed with one pair per epoch).
    posting_m : float, optional
        Grid posting override.
    epoch_a, epoch_b : str, optional
        Epochs to compare (default: first and last).
    pairs : str
        "same-kind" (default: satellite–satellite and aerial–aerial pairs) or "all".
    derive_buildings : bool
        Without footprints, derive building objects from epoch A's DSM (and new ones from epoch B's) for the
        ``buildings`` layer (:mod:`geocd.change.dsm_buildings`); with footprints, the layer holds them (and the new
        buildings of the change map outside them) whatever this says.
    screen : ScreenParams, optional
        Run the 2-D screen first and the stereo only on the tiles it flags (:mod:`geocd.screen.tiered`).
    screen_tile_cells : int
        Side of the screen's tiles (cells).
    """

    stereo: Any = field(default_factory=change_stereo_params)
    consistency: ConsistencyParams = ConsistencyParams()
    change: ChangeParams = ChangeParams()
    buildings: BuildingParams = BuildingParams()
    region_confidence: float = 99.0
    model_path: str | None = None
    posting_m: float | None = None
    epoch_a: str | None = None
    epoch_b: str | None = None
    pairs: str = "same-kind"
    derive_buildings: bool = True
    screen: Any = None
    screen_tile_cells: int = 128

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["stereo"] = self.stereo.to_dict()
        for k in ("consistency", "change", "buildings"):
            d[k] = dataclasses.asdict(getattr(self, k))
        d["screen"] = self.screen.to_dict() if self.screen is not None else None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RunConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ConfigError(f"unknown run configuration keys {sorted(unknown)}; known: {sorted(known)}")
        kw = dict(d)
        if "stereo" in kw:
            kw["stereo"] = change_stereo_params(kw["stereo"])
        if kw.get("screen") is not None:
            from .screen import ScreenParams

            kw["screen"] = ScreenParams.from_dict(dict(kw["screen"]))
        for k, c in (("consistency", ConsistencyParams), ("change", ChangeParams), ("buildings", BuildingParams)):
            if k in kw:
                sub = dict(kw[k])
                for t in ("confidences",):
                    if t in sub:
                        sub[t] = tuple(sub[t])
                try:
                    kw[k] = c(**sub)
                except TypeError as exc:
                    raise ConfigError(f"bad '{k}' configuration: {exc}") from exc
        return cls(**kw)

    @classmethod
    def load(cls, path: os.PathLike | str) -> "RunConfig":
        import yaml

        p = Path(path)
        try:
            d = yaml.safe_load(p.read_text(encoding="utf-8"))
        except Exception as exc:
            raise ConfigError(
                f"cannot read the run configuration {p}: {' '.join(str(exc).split())[:200]}; give "
                "the run_config.json a run wrote"
            ) from exc
        if not isinstance(d, dict) or not d:
            raise ConfigError(
                f"the run configuration {p} is {'empty' if not d else 'not a mapping of parameters'}; "
                "give the run_config.json a run wrote (or leave --config out for the defaults)"
            )
        return cls.from_dict(d)


def _dem_epoch(spec, grid, name: str) -> DEMAsEpoch:
    from .io.raster import read_dem

    dem = read_dem(spec.path, grid=grid, vertical_datum=spec.vertical_datum).to_ellipsoidal()
    return DEMAsEpoch(dem.height_m, grid, name=f"{name}:dem")


#: the quick-look's orthos are computed on at most this many cells per side (a panel is ~540 pixels wide)
QUICKLOOK_MAX_CELLS = 800


def _quicklook_view(manifest, epoch, grid, surface_m: np.ndarray | None):
    """What the run's quick-look shows of one epoch: an ortho of its first image on its surface, else the surface.

    The ortho is a classic one (no occlusion test: every cell takes the pixel the camera sees there) on the
    epoch's median surface with its holes filled by the nearest height, through the run's (corrected) camera,
    on a grid of the same bounds with at most :data:`QUICKLOOK_MAX_CELLS` cells per side. An epoch without
    images, or whose image cannot be orthorectified, is shown by its surface (a hillshade).
    """
    from affine import Affine

    from .change.dsm_buildings import fill_gaps
    from .change.plots import QuickLookView
    from .geodesy import AOIGrid
    from .ortho import OrthoParams, orthorectify
    from .ortho.pipeline import read_image_for_grid
    from .stereo.scene import load_epoch_images

    if surface_m is None or not np.isfinite(surface_m).any() or not epoch.images:
        return QuickLookView(surface_m=surface_m)
    H, W = grid.shape
    k = max(1, math.ceil(max(H, W) / QUICKLOOK_MAX_CELLS))
    Hc, Wc = math.ceil(H / k), math.ceil(W / k)
    coarse = AOIGrid(grid.crs, grid.transform @ Affine.scale(W / Wc, H / Hc), Wc, Hc)
    rows = np.minimum(((np.arange(Hc) + 0.5) * H / Hc).astype(int), H - 1)
    cols = np.minimum(((np.arange(Wc) + 0.5) * W / Wc).astype(int), W - 1)
    dsm = fill_gaps(np.asarray(surface_m, np.float64)[np.ix_(rows, cols)])
    try:
        im = load_epoch_images(manifest, epoch)[0]
        lo, hi = float(dsm.min()), float(dsm.max())
        data, valid, c0, r0, _ = read_image_for_grid(im.path, im.camera, coarse, lo, hi)
        res = orthorectify(
            data, im.camera, coarse, dsm, valid=valid, col0=c0, row0=r0, params=OrthoParams(occlusion=False)
        )
    except (GeoCDError, OSError, ValueError) as exc:
        logger.info("quick-look: no ortho of %s (%s); its surface is shown", epoch.name, exc)
        return QuickLookView(surface_m=surface_m)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        grey = np.nanmean(np.asarray(res.values, np.float32), axis=0)
    grey[~res.observed] = np.nan
    when = f", {epoch.date.isoformat()}" if getattr(epoch, "date", None) else ""
    return QuickLookView(image=grey, surface_m=surface_m, label=f"ortho of {im.name}{when}")


def _building_layer(
    footprints,
    res,
    grid,
    recs_a,
    recs_b,
    model,
    report_confidence: float,
    name_a: str,
    name_b: str,
    params=None,
    building_params: BuildingParams | None = None,
):
    """The run's building layer and the ground model under it, from the epochs' reconstructions: their median
    surfaces into :func:`geocd.change.dsm_buildings.building_layer`."""
    from .change.dsm_buildings import building_layer

    return building_layer(
        footprints,
        res,
        grid,
        z_a=epoch_surface(recs_a),
        z_b=epoch_surface(recs_b),
        model=model,
        report_confidence=report_confidence,
        epoch_a=name_a,
        epoch_b=name_b,
        params=params,
        building_params=building_params,
    )


def run_building_layer(
    footprints,
    res,
    grid,
    recs_a,
    recs_b,
    model,
    config: RunConfig = RunConfig(),
    name_a: str = "A",
    name_b: str = "B",
):
    """The building layer ``geocd run`` writes (layer ``buildings`` of ``sc_changes.gpkg``) and the ground model
    under it, from a change test's result with the run's parameters.

    Parameters
    ----------
    footprints : GeoDataFrame or None
        The footprints (``geocd run`` reads the manifest's, or ``--footprints``, in the grid's CRS); None:
        buildings derived from the DSMs.
    res : geocd.consistency.ChangeResult on ``grid`` (``config.region_confidence`` among its levels)
    recs_a, recs_b : the epochs' pair-DEMs (their median surfaces are the epochs' surfaces)
    model : SelfConsistencyModel (for the volumes' σ)
    config : RunConfig
        ``region_confidence`` (the reported level) and ``buildings`` (the footprint rules) are used.
    name_a, name_b : the epochs' names

    Returns
    -------
    (GeoDataFrame, dtm) as :func:`geocd.change.dsm_buildings.building_layer` (before a tiered run's
    :func:`mark_not_examined`).
    """
    from .change.dsm_buildings import DSMBuildingParams

    bp = config.buildings
    return _building_layer(
        footprints,
        res,
        grid,
        recs_a,
        recs_b,
        model,
        config.region_confidence,
        name_a,
        name_b,
        DSMBuildingParams(
            min_observed=bp.min_observed,
            min_changed=bp.min_changed,
            changed_part=bp.changed_part,
            split_changed=bp.split_changed,
            split_steps=bp.split_steps,
        ),
        building_params=bp,
    )


def mark_not_examined(buildings, grid, examined: np.ndarray | None):
    """Buildings classed ``unobserved`` with cells the 3-D stage did not examine → class ``not examined``.

    Adds ``frac_examined`` (share of the footprint's grid cells in examined tiles). A building the
    tiered run never looked at is reported as not examined, not as unobserved or unchanged.
    """
    if buildings is None or examined is None or not len(buildings):
        return buildings
    from rasterio.features import rasterize
    from scipy import ndimage as ndi

    g = buildings.to_crs(grid.crs).geometry
    n = len(g)
    labels = rasterize(
        [(geom, i + 1) for i, geom in enumerate(g)],
        out_shape=grid.shape,
        transform=grid.transform,
        fill=0,
        dtype="int32",
    )
    idx = np.arange(1, n + 1)
    cells = np.asarray(ndi.sum(np.ones(grid.shape), labels, idx))
    # a footprint with no cell on the grid was not for the 3-D stage to examine: it stays as it is
    frac = np.where(cells > 0, np.asarray(ndi.sum(examined, labels, idx)) / np.maximum(cells, 1), 1.0)
    out = buildings.copy()
    out["frac_examined"] = np.round(frac, 4)
    hit = (out["class"].to_numpy() == "unobserved") & (frac < 1.0)
    if hit.any():
        out.loc[hit, "class"] = "not examined"
        if "rule" in out:
            out.loc[hit, "rule"] = [
                f"not examined: {100 * (1 - f):.0f}% of its cells in tiles the screen did not flag" for f in frac[hit]
            ]
    from .change.building_layer import order_columns

    return order_columns(out)


def _check_epochs_overlap(m) -> None:
    """Epochs whose images cover different places cannot be compared: a clear error before any stereo."""
    from .geodesy import as_crs, utm_crs_for
    from .orientation.pipeline import check_epoch_overlap
    from .stereo.scene import load_epoch_images

    by_epoch = {e.name: load_epoch_images(m, e) for e in m.epochs if e.images}
    if len(by_epoch) < 2:
        return
    cam = next(iter(by_epoch.values()))[0].camera
    hr = cam.height_range() or (0.0, 0.0)
    h = 0.5 * (hr[0] + hr[1])
    crs = as_crs(m.aoi.crs) if m.aoi is not None and m.aoi.crs else None
    if crs is None:
        c = cam.footprint(h).centroid
        crs = utm_crs_for(c.x, c.y)
    check_epoch_overlap(by_epoch, crs, h, m.aoi.bounds if m.aoi is not None and m.aoi.crs else None)


def run_orientation(run_dir: os.PathLike | str, summary: dict) -> dict | None:
    """A run folder's orientation summary: its run summary's, else (a run re-tested from another run's
    pair-DEMs, whose summary has none) that of the ``orientation/orientation.json`` its folder holds."""
    if summary.get("orientation") is not None:
        return summary["orientation"]
    rep = Path(run_dir) / "orientation" / "orientation.json"
    return orientation_summary(json.loads(rep.read_text())) if rep.is_file() else None


def orientation_summary(report: dict) -> dict:
    """The part of an orientation report a run summary carries (applied or not, why, residuals)."""
    keys = ("applied", "reason", "model", "tracks", "observations", "before", "after", "held_out")
    out = {k: report[k] for k in keys if k in report}
    out["corrections_px"] = dict(zip(report.get("images", []), report.get("corrections", [])))
    return out


def run(
    manifest,
    *,
    out_dir: os.PathLike | str | None = None,
    config: RunConfig = RunConfig(),
    progress: Progress | None = None,
    footprints: os.PathLike | str | None = None,
    log_file: bool = True,
) -> dict[str, Any]:
    """Run the whole self-consistency change detection on a manifest.

    Progress goes to ``progress`` and to the standard :mod:`logging` module: INFO lines on the logger
    ``"geocd"`` for each stage and each 5 % (``logging.basicConfig(level=logging.INFO)`` shows them).

    Parameters
    ----------
    manifest : Manifest or path
        The scene: a manifest, its file, or a folder holding one.
    out_dir : path, optional
        Output folder [the manifest's output folder].
    config : RunConfig
        Parameters of every step.
    progress : callable, optional
        ``progress(fraction, message)``; it may raise :class:`~geocd.errors.CancelledError` to stop the run.
    footprints : path, optional
        Building footprints (a vector file) for the ``buildings`` layer (default: the manifest's).
    log_file : bool
        Write the run's log, ``geocd_run.log``, into ``out_dir`` (the one ``geocd run`` writes: parameters,
        progress, warnings, products, the error if it fails). The CLI writes its own and passes False.

    Returns
    -------
    dict: outputs ({name: path}), summary (dict written to run_summary.json).
    """
    from .io.manifest import Manifest, load_manifest

    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    out = Path(out_dir) if out_dir is not None else m.output_dir()
    runlog = None
    if log_file:
        runlog = RunLog(
            "run",
            {
                "manifest": str(getattr(m, "path", None) or manifest),
                "out_dir": str(out),
                "footprints": footprints,
                "config": config.to_dict(),
            },
        )
        try:
            runlog.open(out)
        except OSError as exc:
            warnings.warn(
                f"cannot write the log file {out / log_file_name('run')} ({exc.strerror or exc})",
                UserWarning,
                stacklevel=2,
            )
            runlog = None
    t0 = time.monotonic()
    prog = LoggedProgress("run", progress, runlog)
    old_show = warnings.showwarning

    def _show(message, category, filename, lineno, file=None, line=None):
        if runlog is not None:
            runlog.line(f"WARNING {category.__name__}: {message}")
        old_show(message, category, filename, lineno, file, line)

    if runlog is not None:
        warnings.showwarning = _show
    try:
        res = _run(m, out, config, prog, footprints)
        logger.info("run done in %.1f s; products in %s", time.monotonic() - t0, out)
        if runlog is not None:
            for k, v in res["outputs"].items():
                runlog.line(f"OUTPUT {k}: {v}")
            runlog.line(f"done in {time.monotonic() - t0:.1f} s")
    except BaseException as exc:
        logger.info("run failed after %.1f s: %s: %s", time.monotonic() - t0, type(exc).__name__, exc)
        if runlog is not None:
            runlog.line(f"ERROR {type(exc).__name__}: {exc}")
            if not isinstance(exc, (GeoCDError, KeyboardInterrupt)):
                runlog.lines("".join(traceback.format_exception(type(exc), exc, exc.__traceback__)))
            runlog.line(f"failed after {time.monotonic() - t0:.1f} s")
        raise
    finally:
        if warnings.showwarning is _show:
            warnings.showwarning = old_show
        if runlog is not None:
            runlog.close()
    return res


def _run(m, out: Path, config: RunConfig, prog: Progress, footprints) -> dict[str, Any]:
    from .stereo.pipeline import run_stereo

    out.mkdir(parents=True, exist_ok=True)
    ea, eb = pick_epochs(m, config.epoch_a, config.epoch_b)
    model = SelfConsistencyModel.load(config.model_path) if config.model_path else None
    for e in (ea, eb):
        if len(e.images) < 2 and e.dem is None:
            raise ConfigError(
                f"epoch {e.name!r} has {len(e.images)} image(s) and no DEM: a stereo pair needs two images. Add an "
                "image, or give a DEM standing for this epoch (epochs[].dem)"
            )
    stereo_epochs = [e.name for e in m.epochs if len(e.images) >= 2]
    from .orientation import orient_manifest
    from .stereo.pipeline import early_resource_check
    from .stereo.scene import load_epoch_images

    for e in m.epochs:  # the images' cameras first: a damaged camera file is the first thing said
        load_epoch_images(m, e)
    early_resource_check(m, None, config.posting_m, out)  # a job too large for the machine stops before any step
    _check_epochs_overlap(m)  # footprints only: epochs of two different places are said before any step
    if model is None and not any(len(e.images) >= 3 for e in m.epochs):
        # learning the model needs two pair-DEMs of one epoch: three views; say so before hours of stereo
        raise ConfigError(
            "no epoch has three or more images (two or more stereo pairs), so the self-consistency distribution "
            "cannot be learned from this scene; pass a scene-class model learned on a scene of the same class "
            "(--model MODEL.json, made with `geocd consistency`; examples/kahramanmaras/marseille_urban_model.json "
            "is one for urban Pléiades scenes), or add a third image to an epoch"
        )

    prog(0.0, "relative orientation")
    m, orientation = orient_manifest(
        m, out_dir=out, stereo_params=config.stereo, progress=sub_progress(prog, 0.0, 0.1, "orientation: ")
    )
    prog(0.1, "stereo")
    if config.screen is not None:  # tiered: the 2-D screen, then stereo on the flagged tiles only
        from .screen.tiered import run_stereo_screened

        st = run_stereo_screened(
            m,
            out=out,
            stereo_params=config.stereo,
            screen_params=config.screen,
            epochs=stereo_epochs,
            pairs=config.pairs,
            posting_m=config.posting_m,
            epoch_a=ea.name,
            epoch_b=eb.name,
            tile_cells=config.screen_tile_cells,
            progress=sub_progress(prog, 0.1, 0.75, "screen + stereo: "),
        )
    else:
        st = run_stereo(
            m,
            epochs=stereo_epochs,
            out_dir=out,
            params=config.stereo,
            posting_m=config.posting_m,
            keep_arrays=True,
            pairs=config.pairs,
            orient=False,
            progress=sub_progress(prog, 0.1, 0.75, "stereo: "),
        )
    by_epoch: dict[str, list] = {}
    for key, pdem in st["pairs"].items():
        by_epoch.setdefault(pdem.epoch or key.split("/")[0], []).append(pdem)
    res = run_change(
        m,
        by_epoch,
        st["grid"],
        out_dir=out,
        config=config,
        model=model,
        progress=sub_progress(prog, 0.75, 1.0),
        footprints=footprints,
        stereo_outputs=st["outputs"],
        orientation=orientation,
        examined=st.get("examined"),
        calibration_cells=st.get("calibration_cells"),
    )
    if "screen" in st:
        res["summary"]["screen"] = st["screen"]
        res["outputs"].update(st["screen_outputs"])
        res["summary"]["outputs"].update({k: str(v) for k, v in st["screen_outputs"].items()})
    # the stereo step's completeness warnings and the pairs it left out (also on screen and in the log)
    res["summary"]["warnings"] = list(st.get("warnings", []))
    res["summary"]["notes"] = list(st.get("notes", []))
    write_text_atomic(out / "run_summary.json", json.dumps(res["summary"], indent=2, default=str))
    return res


def run_change(
    manifest,
    by_epoch: dict[str, list],
    grid,
    *,
    out_dir: os.PathLike | str,
    config: RunConfig = RunConfig(),
    model: SelfConsistencyModel | None = None,
    progress: Progress | None = None,
    footprints: os.PathLike | str | None = None,
    stereo_outputs: dict | None = None,
    orientation: dict | None = None,
    examined: np.ndarray | None = None,
    calibration_cells: np.ndarray | None = None,
) -> dict[str, Any]:
    """Everything of :func:`run` after the stereo: baseline, change test, buildings, products.

    Parameters
    ----------
    manifest : Manifest
    by_epoch : {epoch name: [pair-DEMs]} on ``grid`` (e.g. read back with :func:`geocd.stereo.read_pair_dem`)
    grid : AOIGrid
    model : a scene-class model (default: ``config.model_path``, else learned here)
    stereo_outputs : {name: path} of the pair-DEMs, listed in the outputs and summary
    orientation : the cross-epoch relative orientation report (summarised in run_summary.json), if one was made
    examined : bool (rows, cols), optional: the cells the 3-D stage examined (a tiered run's flagged tiles);
        the others get the change-mask code ``NOT_EXAMINED`` and buildings unobserved there the class
        ``not examined``
    calibration_cells : bool (rows, cols), optional: fit the transfer calibration (when the model asks for
        one) on these cells only — a tiered run's examined cells that the screen calls unchanged, since
        its examined tiles were chosen for their change (:func:`geocd.screen.tiered.fit_calibration_on`)
    """
    from .change.products import write_change_products
    from .io.atomic import write_text_atomic
    from .io.vector import read_footprints

    prog = ensure_progress(progress)
    m = manifest
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ea, eb = pick_epochs(m, config.epoch_a, config.epoch_b)
    if model is None and config.model_path:
        model = SelfConsistencyModel.load(config.model_path)
    recs_a = by_epoch.get(ea.name, []) or ([_dem_epoch(ea.dem, grid, ea.name)] if ea.dem else [])
    recs_b = by_epoch.get(eb.name, []) or ([_dem_epoch(eb.dem, grid, eb.name)] if eb.dem else [])
    if model is None:
        groups = [g for g in by_epoch.values() if len(g) >= 2]
        if not groups:
            raise ConfigError(
                "no epoch has two or more image pairs, so the self-consistency distribution cannot be learned here; "
                "pass a scene-class model learned on another scene of the same class (--model MODEL.json, made with "
                "`geocd consistency`)"
            )
        prog(0.05, "learning the self-consistency distribution")
        prov = {
            "scene": m.name,
            "scene_class": m.scene_class,
            "epochs": {e: [p.name for p in g] for e, g in by_epoch.items() if len(g) >= 2},
            "dates": {e.name: e.date.isoformat() if e.date else None for e in m.epochs},
            "sensors": {e.name: e.sensor for e in m.epochs},
            "gsd_m": grid.posting_m,
            "score": config.stereo.score,
        }
        model = learn_self_consistency(
            groups, config.consistency, provenance=prov, progress=sub_progress(prog, 0.05, 0.3)
        )
    model_path = model.save(out / "self_consistency_model.json")
    prog(0.3, "cross-epoch change test")
    change_params = config.change
    if config.region_confidence not in change_params.confidences:  # the reported level is always tested
        change_params = dataclasses.replace(
            change_params, confidences=tuple(sorted({*change_params.confidences, config.region_confidence}))
        )
    cal = offsets = None
    if calibration_cells is not None:
        from .screen.tiered import fit_calibration_on

        cal, offsets = fit_calibration_on(recs_a, recs_b, model, change_params, calibration_cells)
    res = change_test(
        recs_a,
        recs_b,
        model,
        change_params,
        progress=sub_progress(prog, 0.3, 0.7),
        offsets=offsets if cal is not None else None,
        calibration=cal,
    )
    buildings = ground_path = None
    fp_path = footprints or (m.footprints.path if m.footprints is not None else None)
    if fp_path is not None or config.derive_buildings:
        prog(0.7, "buildings")
        fps = None
        if fp_path is not None:
            fps = read_footprints(
                fp_path, crs=grid.crs, layer=m.footprints.layer if (m.footprints and not footprints) else None
            )
        buildings, ground = run_building_layer(fps, res, grid, recs_a, recs_b, model, config, ea.name, eb.name)
        buildings = mark_not_examined(buildings, grid, examined)
        if ground is not None:
            from .io.raster import write_cog

            ground_path = write_cog(
                out / "sc_ground_model.tif",
                {"ground_m": ground.astype(np.float32)},
                grid,
                tags={
                    "method": f"progressive morphological filter of the {ea.name} DSM",
                    "vertical_datum": "ellipsoid",
                },
            )
    prog(0.8, "writing products")
    surface_a, surface_b = epoch_surface(recs_a), epoch_surface(recs_b)
    paths = write_change_products(
        out,
        res,
        grid,
        method="self-consistency",
        epoch_a=ea.name,
        epoch_b=eb.name,
        region_confidence=config.region_confidence,
        model=model,
        buildings=buildings,
        provenance={"manifest": str(m.path or m.root), "config": "run_config.json"},
        prefix="sc",
        backdrop_m=surface_b,
        backdrop_a_m=surface_a,
        quicklook_views=(_quicklook_view(m, ea, grid, surface_a), _quicklook_view(m, eb, grid, surface_b)),
        examined=examined,
    )
    paths["model"] = model_path
    if ground_path is not None:
        paths["ground_model"] = ground_path
    paths.update({f"stereo:{k}": v for k, v in (stereo_outputs or {}).items()})
    cfg_path = write_text_atomic(out / "run_config.json", json.dumps(config.to_dict(), indent=2, default=list))
    observed = res.observed
    summary = {
        "geocd_run": 1,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "manifest": str(m.path or m.root),
        "epoch_a": ea.name,
        "epoch_b": eb.name,
        "grid": grid.to_dict(),
        "pairs": {e: [p.name for p in g] for e, g in by_epoch.items()},
        "completeness": {p.name: round(p.completeness, 4) for g in by_epoch.values() for p in g},
        "observed_fraction": round(float(observed.mean()), 4),
        **({"examined_fraction": round(float(np.mean(examined)), 4)} if examined is not None else {}),
        "changed_fraction": {
            f"{c:g}": round(float((res.changed_at(c) != 0)[observed].mean()), 5) for c in res.confidences
        },
        "model": {
            "bins": len(model.score_centres),
            "match_pairs": int(model.bin_counts.sum()),
            "learned_here": config.model_path is None,
            "calibration": res.calibration.to_dict() if res.calibration is not None else "none",
            **({"calibration_fitted_on": "examined cells the screen calls unchanged"} if cal is not None else {}),
        },
        "outputs": {k: str(v) for k, v in paths.items()},
    }
    if buildings is not None:
        from .change.building_layer import SOURCE_FOOTPRINTS, source_dsm, summarize

        summary["buildings"] = summarize(buildings, SOURCE_FOOTPRINTS if fp_path is not None else source_dsm(ea.name))
    else:
        summary["buildings"] = {
            "source": None,
            "classes": {},
            "volume_lost_m3": None,
            "reason": (
                "no footprints and derive_buildings is off"
                if fp_path is None and not config.derive_buildings
                else "an epoch has no height to derive buildings from"
            ),
        }
    if orientation is not None:
        summary["orientation"] = orientation_summary(orientation)
    write_text_atomic(out / "run_summary.json", json.dumps(summary, indent=2, default=str))
    paths["config"] = cfg_path
    paths["summary"] = out / "run_summary.json"
    prog(1.0, "done")
    return {
        "outputs": paths,
        "summary": summary,
        "result": res,
        "model": model,
        "grid": grid,
        "pairs": by_epoch,
        "buildings": buildings,
    }
