"""``geocd run``, ``geocd consistency`` and ``geocd change``: the self-consistency change detection."""

from __future__ import annotations

import json
from pathlib import Path

import click

from .common import check_confidence
from .vocabulary import vertical_datum_option


def _confidences(values) -> tuple[float, ...]:
    return tuple(sorted(set(float(v) for v in values))) if values else (90.0, 95.0, 99.0)


@click.command("run")
@click.argument("manifest", type=click.Path(path_type=str), default="sample_aoi")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(path_type=str),
    default=None,
    help="Output folder (default: the manifest's 'output:' if it names one, else ./geocd_out/<scene name>).",
)
@click.option(
    "--model",
    "model_path",
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    default=None,
    help="Scene-class self-consistency model (JSON) to use instead of learning one here.",
)
@click.option(
    "--config",
    "config_path",
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    default=None,
    help="Run configuration (YAML/JSON, same tree as the run_config.json written by a run).",
)
@click.option(
    "--confidence",
    "confidences",
    type=float,
    multiple=True,
    callback=check_confidence,
    help="Confidence levels in percent (repeatable; default 90 95 99).",
)
@click.option(
    "--report-confidence",
    type=float,
    default=None,
    callback=check_confidence,
    help="Level in percent for the change mask, regions and buildings (default 99).",
)
@click.option(
    "--footprints",
    type=click.Path(exists=True, path_type=str),
    default=None,
    help="Building footprints to attribute (default: the manifest's).",
)
@click.option("--posting", "posting_m", type=float, default=None, help="Grid posting, metres.")
@click.option("--epoch-a", default=None, help="Earlier epoch (default: the first).")
@click.option("--epoch-b", default=None, help="Later epoch (default: the last).")
@click.option(
    "--pairs",
    type=click.Choice(["same-kind", "all"]),
    default=None,
    help="Image pairs to match: same camera kind only (default) or all.",
)
@click.option(
    "--screen",
    "screen",
    is_flag=True,
    help="Tiered run: the fast 2-D screen first (geocd screen), stereo and the change test only on "
    "windows around the tiles it flags, or on the whole grid when those windows would read all of "
    "it. A tile is flagged when its area above the lower of the no-change pair's and the compared "
    "pair's own 99 % dissimilarity quantiles exceeds chance, or when a flagged change reaches into "
    "it (OUT/screen holds its layers; run_summary.json: screen.flag_rule, screen.stereo_plan).",
)
@click.option(
    "--screen-feature",
    type=click.Choice(["patch", "daisy", "randbank", "cnn"]),
    default="patch",
    show_default=True,
    help="Grid feature of the screen (--screen); cnn needs --screen-backbone and --screen-weights.",
)
@click.option(
    "--screen-backbone",
    default=None,
    help="--screen-feature cnn: the backbone (e.g. efficientnet_lite0; see geocd screen --backbone).",
)
@click.option(
    "--screen-weights",
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    default=None,
    help="--screen-feature cnn: the weights file (never downloaded; see geocd screen --weights).",
)
@click.option("--screen-layer", default=None, help="--screen-feature cnn: the layer (default: the backbone's).")
@click.option(
    "--screen-tile",
    "screen_tile",
    type=int,
    default=128,
    show_default=True,
    help="Side of the screen's tiles, cells, ≥ 64 (--screen); cells of unflagged tiles are coded "
    "-127 'not examined' in the change mask.",
)
@click.option(
    "--calibration",
    type=click.Choice(["auto", "pair", "none"]),
    default=None,
    help="Fit a transferred model's scale and a slope × misregistration term to the tested comparisons "
    "(pair), use the model as learned (none), or pair only when the model was learned elsewhere "
    "(auto, the default).",
)
@click.pass_context
def run(
    ctx,
    manifest,
    out_dir,
    model_path,
    config_path,
    confidences,
    report_confidence,
    footprints,
    posting_m,
    epoch_a,
    epoch_b,
    pairs,
    screen,
    screen_feature,
    screen_backbone,
    screen_weights,
    screen_layer,
    screen_tile,
    calibration,
):
    """Full run on MANIFEST (default: sample_aoi): stereo → self-consistency baseline → change test → layers.

    Writes pair-DEMs (OUT/stereo), the scene-class model, change rasters (COG + QGIS styles), the changes/buildings/
    curves GeoPackage, plots, run_config.json and run_summary.json.
    """
    from .common import require_inputs, resolve_out_dir, session

    require_inputs(manifest, what="manifest")
    from ..io.manifest import load_manifest

    m = load_manifest(manifest)
    out = resolve_out_dir(out_dir if out_dir is not None else m.output, m.name, create=False)
    from ..io.vector import check_footprints_file

    if footprints is not None:
        check_footprints_file(footprints)
    elif m.footprints is not None:
        check_footprints_file(m.footprints.path, m.footprints.layer)
    from ..consistency import ChangeParams, ConsistencyParams
    from ..io.outputs import open_outputs
    from ..pipeline import PRODUCTS, RunConfig, run as run_pipeline
    from . import emit_result, make_progress

    cfg = RunConfig.load(config_path) if config_path else RunConfig()
    screen_feature_spec = None
    if screen:
        from ..screen import FeatureSpec

        screen_feature_spec = FeatureSpec(
            kind=screen_feature, backbone=screen_backbone, weights=screen_weights, layer=screen_layer
        )
        if screen_feature == "cnn":
            screen_feature_spec.build()  # the weights read and matched to the backbone before any work
    open_outputs(out, inputs=[*m.input_paths(), model_path, config_path, footprints, screen_weights], products=PRODUCTS)
    sess = session(ctx)
    sess.open_log(out)
    changes = {}
    if confidences:
        c = _confidences(confidences)
        changes["consistency"] = ConsistencyParams(**{**cfg.consistency.__dict__, "confidences": c})
        changes["change"] = ChangeParams(**{**cfg.change.__dict__, "confidences": c})
    if calibration is not None:
        changes["change"] = ChangeParams(**{**changes.get("change", cfg.change).__dict__, "calibration": calibration})
    for k, v in (
        ("model_path", model_path),
        ("region_confidence", report_confidence),
        ("posting_m", posting_m),
        ("epoch_a", epoch_a),
        ("epoch_b", epoch_b),
        ("pairs", pairs),
    ):
        if v is not None:
            changes[k] = v
    if screen_feature_spec is not None:
        from ..screen import ScreenParams

        changes["screen"] = ScreenParams(feature=screen_feature_spec)
        changes["screen_tile_cells"] = int(screen_tile)
    import dataclasses

    cfg = dataclasses.replace(cfg, **changes)
    progress = make_progress(ctx, "run")
    try:
        res = run_pipeline(m, out_dir=out, config=cfg, progress=progress, footprints=footprints, log_file=False)
    finally:
        progress.close()
    s = res["summary"]
    sess.say(
        f"compared {s['epoch_a']} → {s['epoch_b']} on a {s['grid']['width']}x{s['grid']['height']} grid; "
        f"observed {100 * s['observed_fraction']:.1f}% of cells; changed: "
        + ", ".join(f"{100 * v:.2f}% at {k}%" for k, v in s["changed_fraction"].items())
    )
    from ..change.building_layer import summary_line

    sess.say(summary_line(s.get("buildings")))
    if "screen" in s:
        sc = s["screen"]
        sess.say(
            f"screen ({sc['feature']}): {sc['flagged_tiles']} of {sc['tiles']} tiles flagged, stereo on "
            f"{100 * sc['stereo_cell_fraction']:.1f}% of the grid; screen {sc['screen_seconds']:.1f} s, "
            f"stereo {sc['stereo_seconds']:.1f} s"
        )
    sess.data(
        **{k: s[k] for k in ("epoch_a", "epoch_b", "observed_fraction", "changed_fraction", "buildings") if k in s}
    )
    n_pairs = sum(1 for k in res["outputs"] if k.startswith("stereo:"))
    if n_pairs:
        sess.say(f"{n_pairs} pair-DEMs in {out / 'stereo'}")
    emit_result(ctx, {k: v for k, v in res["outputs"].items() if not k.startswith("stereo:")})


def _read_pairs(paths):
    import warnings

    from ..stereo import read_pair_dem
    from ..stereo.params import isolation_cells, surface_median_cells

    pairs = [read_pair_dem(p) for p in paths]
    # the self-consistency test models each cell's own match: a pair-DEM whose heights or validity depend on its
    # neighbours' (a surface median, the neighbour-agreement test) makes more false changes
    for made_with, why, cells in (
        ("a surface median", "a median correlates neighbouring errors (more false changes)", surface_median_cells),
        (
            "the neighbour-agreement test",
            "a validity that depends on the neighbours' heights made more false changes on sample_aoi",
            isolation_cells,
        ),
    ):
        names = [p.name for p in pairs if cells(p.meta.get("params") or {}) != 1]
        if names:
            warnings.warn(
                f"pair-DEM(s) {', '.join(names)} were matched with {made_with}: the self-consistency test models "
                f"each cell's own match, and {why}; for change detection make them with `geocd stereo "
                "--surface-median 1 --isolation-min-cells 1` (as geocd run does)",
                UserWarning,
                stacklevel=2,
            )
    return pairs


def _is_consistency_model(p: Path) -> bool:
    """Whether ``p`` is a self-consistency model geocd wrote (JSON with its format key)."""
    with open(p, "rb") as fh:
        if not fh.read(64).lstrip().startswith(b"{"):
            return False
    d = json.loads(p.read_text(encoding="utf-8"))
    return isinstance(d, dict) and "geocd_self_consistency_model" in d


@click.command("consistency")
@click.argument("pair_dems", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=str))
@click.option(
    "--out",
    "out_path",
    default=None,
    type=click.Path(dir_okay=False, path_type=str),
    help="Scene-class model to write (JSON; default: ./geocd_out/consistency/self_consistency_model.json).",
)
@click.option(
    "--group-by",
    type=click.Choice(["epoch", "none"]),
    default="epoch",
    show_default=True,
    help="Compare pair-DEMs within each epoch (from their tags), or all together (one static scene).",
)
@click.option(
    "--confidence",
    "confidences",
    type=float,
    multiple=True,
    callback=check_confidence,
    help="Levels in percent (default 90 95 99).",
)
@click.option("--scene-class", default="", help="Scene class recorded in the model (e.g. urban, suburban, rural).")
@click.option("--sensor", default="", help="Sensor recorded in the model.")
@click.option("--bins", "n_bins", type=int, default=24, show_default=True, help="Number of score bins.")
@click.option(
    "--plot",
    "plot_path",
    type=click.Path(dir_okay=False, path_type=str),
    default=None,
    help="Also write the scatter + curves PNG.",
)
@click.option(
    "--overwrite",
    is_flag=True,
    help="Replace an existing --out file even when it is not a geocd self-consistency model.",
)
@click.pass_context
def consistency(ctx, pair_dems, out_path, group_by, confidences, scene_class, sensor, n_bins, plot_path, overwrite):
    """Learn a self-consistency model (stage 1) from pair-DEMs of a static scene (GeoTIFFs from `geocd stereo`)."""
    from ..consistency import ConsistencyParams, learn_self_consistency
    from ..io.outputs import open_outputs, refuse_foreign_files
    from . import emit_result, make_progress
    from .common import resolve_out_dir, session

    if out_path is None:
        out_path = str(resolve_out_dir(None, "consistency", create=False) / "self_consistency_model.json")
    open_outputs(None, files=[out_path, plot_path], inputs=pair_dems)
    refuse_foreign_files(
        [out_path], _is_consistency_model, what="a geocd self-consistency model (JSON)", force=overwrite
    )
    sess = session(ctx)
    sess.open_log(Path(out_path).parent)
    pairs = _read_pairs(pair_dems)
    groups: dict[str, list] = {}
    for p in pairs:
        groups.setdefault(p.epoch if group_by == "epoch" else "all", []).append(p)
    params = ConsistencyParams(confidences=_confidences(confidences), n_score_bins=n_bins)
    prov = {
        "scene_class": scene_class,
        "sensor": sensor,
        "pair_dems": [str(Path(p).resolve()) for p in pair_dems],
        "gsd_m": pairs[0].grid.posting_m,
        "score": pairs[0].meta.get("score_kind", ""),
    }
    progress = make_progress(ctx, "consistency")
    try:
        model = learn_self_consistency(list(groups.values()), params, provenance=prov, progress=progress)
    finally:
        progress.close()
    outputs = {"model": model.save(out_path)}
    if plot_path:
        from ..change.plots import plot_scatter_curves

        outputs["scatter"] = plot_scatter_curves(model, plot_path)
    sess.say(model.curves_table().to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    emit_result(ctx, outputs)


@click.command("change")
@click.option(
    "--pair-dem-a",
    "a_paths",
    multiple=True,
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    help="Pair-DEM GeoTIFF of the earlier epoch (repeatable).",
)
@click.option(
    "--pair-dem-b",
    "b_paths",
    multiple=True,
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    help="Pair-DEM GeoTIFF of the later epoch (repeatable).",
)
@click.option(
    "--dem-a",
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    default=None,
    help="A DEM standing for the earlier epoch (treated as exact: only the stereo side's uncertainty counts).",
)
@click.option(
    "--dem-b",
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    default=None,
    help="A DEM standing for the later epoch.",
)
@vertical_datum_option(
    "Vertical datum of --dem-a/--dem-b when their files do not say (ellipsoid, egm96, egm2008).",
    dest="dem_vertical_datum",
)
@click.option(
    "--model",
    "model_path",
    required=True,
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    help="Self-consistency model (from `geocd consistency` or a run).",
)
@click.option(
    "--footprints", type=click.Path(exists=True, path_type=str), default=None, help="Footprints to attribute."
)
@click.option(
    "--out",
    "out_dir",
    default=None,
    type=click.Path(file_okay=False, path_type=str),
    help="Output folder (default: ./geocd_out/change).",
)
@click.option(
    "--confidence",
    "confidences",
    type=float,
    multiple=True,
    callback=check_confidence,
    help="Levels in percent (default 90 95 99).",
)
@click.option(
    "--report-confidence",
    type=float,
    default=99.0,
    show_default=True,
    callback=check_confidence,
    help="Level in percent for the change mask, regions and buildings.",
)
@click.option("--combine", type=click.Choice(["majority", "all", "any"]), default="majority", show_default=True)
@click.option(
    "--tiled",
    is_flag=True,
    help="Test tile by tile (whole scenes: bounded memory, resumable, on Dask); the products are the same.",
)
@click.option(
    "--scheduler",
    default=None,
    metavar="SCHEDULER",
    help="Tiled runs (implies --tiled): sync | threads | processes | auto (a local Dask cluster sized to the "
    "machine, the default; this process when there is one tile) | ADDRESS of a running dask.distributed "
    "scheduler (tcp://host:8786).",
)
@click.option(
    "--tile-size",
    type=click.IntRange(64, None),
    default=None,
    help="Tiled runs: cells per tile side [1024] (implies --tiled).",
)
@click.option(
    "--calibration",
    type=click.Choice(["auto", "pair", "none"]),
    default="auto",
    show_default=True,
    help="Fit a transferred model's scale and a slope × misregistration term to the tested comparisons "
    "(pair), use the model as learned (none), or pair only when the model was learned elsewhere "
    "(auto, the default).",
)
@click.pass_context
def change(
    ctx,
    a_paths,
    b_paths,
    dem_a,
    dem_b,
    dem_vertical_datum,
    model_path,
    footprints,
    out_dir,
    confidences,
    report_confidence,
    combine,
    tiled,
    scheduler,
    tile_size,
    calibration,
):
    """Stage 2: test cross-epoch pair-DEMs (or a DEM standing for an epoch) against a self-consistency model."""
    from ..change.products import write_change_products
    from ..consistency import ChangeParams, DEMAsEpoch, SelfConsistencyModel, change_test
    from ..errors import ConfigError
    from ..io.raster import read_dem
    from ..io.vector import read_footprints
    from ..io.outputs import open_outputs
    from . import emit_result, make_progress
    from .common import resolve_out_dir, session

    out_dir = str(resolve_out_dir(out_dir, "change", create=False))
    if tiled or scheduler or tile_size:
        from ..io.raster import check_dem_file

        for d in (dem_a, dem_b):  # read_dem's checks, which the window reads of the tiled test do not make
            if d:
                check_dem_file(d)
    open_outputs(out_dir, inputs=[*a_paths, *b_paths, dem_a, dem_b, model_path, footprints], products=("sc_*",))
    session(ctx).open_log(out_dir)
    if tiled or scheduler or tile_size:
        from ..change.tiled import change_test_tiled, open_reconstruction
        from ..tiling.params import TilingParams

        A = list(a_paths) + (
            [open_reconstruction(dem_a, kind="dem", name="dem_a", vertical_datum=dem_vertical_datum)[0]]
            if dem_a
            else []
        )
        B = list(b_paths) + (
            [open_reconstruction(dem_b, kind="dem", name="dem_b", vertical_datum=dem_vertical_datum)[0]]
            if dem_b
            else []
        )
        params = ChangeParams(
            confidences=tuple(sorted({*_confidences(confidences), float(report_confidence)})),
            combine=combine,
            calibration=calibration,
        )
        tiling = TilingParams(**{k: v for k, v in (("scheduler", scheduler), ("tile_size", tile_size)) if v})
        progress = make_progress(ctx, "change")
        try:
            res = change_test_tiled(
                A,
                B,
                SelfConsistencyModel.load(model_path),
                out_dir,
                params=params,
                tiling=tiling,
                footprints=footprints,
                region_confidence=report_confidence,
                progress=progress,
            )
        finally:
            progress.close()
        session(ctx).say(f"tiled change test: {res.passes} passes, {res.tiles_resumed} tile results resumed")
        emit_result(ctx, res.outputs)
        return
    A, B = _read_pairs(a_paths), _read_pairs(b_paths)
    if not (A or B):
        raise ConfigError(
            "give pair-DEMs of both epochs (--pair-dem-a ... --pair-dem-b ...), or one epoch's pair-DEMs and a DEM for the other"
        )
    grid = (A or B)[0].grid
    for p in A + B:
        if not p.grid.same_as(grid):
            raise ConfigError(
                f"pair-DEM {p.name} is on another grid than {(A or B)[0].name}; run stereo on one AOI grid"
            )
    if dem_a:
        A.append(
            DEMAsEpoch(
                read_dem(dem_a, grid=grid, vertical_datum=dem_vertical_datum).to_ellipsoidal().height_m, grid, "dem_a"
            )
        )
    if dem_b:
        B.append(
            DEMAsEpoch(
                read_dem(dem_b, grid=grid, vertical_datum=dem_vertical_datum).to_ellipsoidal().height_m, grid, "dem_b"
            )
        )
    if not A or not B:
        raise ConfigError(
            "each epoch needs at least one pair-DEM (--pair-dem-a/--pair-dem-b) or a DEM (--dem-a/--dem-b)"
        )
    model = SelfConsistencyModel.load(model_path)
    params = ChangeParams(
        confidences=tuple(sorted({*_confidences(confidences), float(report_confidence)})),
        combine=combine,
        calibration=calibration,
    )
    progress = make_progress(ctx, "change")
    try:
        res = change_test(A, B, model, params, progress=progress)
    finally:
        progress.close()
    buildings = None
    if footprints:
        from ..pipeline import _building_layer

        buildings, _ = _building_layer(
            read_footprints(footprints, crs=grid.crs), res, grid, A, B, model, report_confidence, "A", "B"
        )
    from ..stereo.surface import epoch_surface

    paths = write_change_products(
        out_dir,
        res,
        grid,
        method="self-consistency",
        epoch_a=A[0].epoch if hasattr(A[0], "epoch") else "A",
        epoch_b=B[0].epoch if hasattr(B[0], "epoch") else "B",
        region_confidence=report_confidence,
        model=model,
        buildings=buildings,
        prefix="sc",
        backdrop_a_m=epoch_surface(A),
        backdrop_m=epoch_surface(B),
    )
    emit_result(ctx, paths)
