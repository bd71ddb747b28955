"""``geocd landcover train|predict|integrate``: city-scale land-surface condition (Sakurada's thesis, ch. 6)."""

from __future__ import annotations

import click

from .vocabulary import vertical_datum_option


def _progress(ctx, stage):
    from . import make_progress

    return make_progress(ctx, stage)


def _close(p):
    if hasattr(p, "close"):
        p.close()


def _scene_options(f):
    """Options that place the ground grid and say what the rays meet (shared by the three commands)."""
    opts = [
        click.option(
            "--manifest",
            "manifest_path",
            type=click.Path(exists=True, path_type=str),
            default=None,
            help="Scene manifest: its AOI grid, DEM and footprints (explicit options below win).",
        ),
        click.option(
            "--dem",
            type=click.Path(exists=True, dir_okay=False, path_type=str),
            default=None,
            help="Terrain DEM (any CRS/datum; its grid is the default AOI grid).",
        ),
        vertical_datum_option(
            "Vertical datum of the DEM when its file does not say (ellipsoid, egm96, egm2008).", dest="dem_datum"
        ),
        click.option(
            "--footprints",
            type=click.Path(exists=True, dir_okay=False, path_type=str),
            default=None,
            help="Building footprints (polygons): occupancy input, extruded by --height-field as the "
            "surface that stops rays.",
        ),
        click.option(
            "--height-field",
            default=None,
            help="Footprint attribute with the building height above ground, m (default: height_m, height, ...).",
        ),
        click.option(
            "--dsm",
            type=click.Path(exists=True, dir_okay=False, path_type=str),
            default=None,
            help="A DSM (e.g. from geocd stereo): the surface rays meet where it has data.",
        ),
        click.option(
            "--bounds",
            nargs=4,
            type=float,
            default=None,
            metavar="LEFT BOTTOM RIGHT TOP",
            help="AOI bounds in the grid CRS (default: the manifest's AOI, else the DEM's extent).",
        ),
        click.option(
            "--posting",
            "posting_m",
            type=float,
            default=None,
            help="Grid posting in metres (default: the manifest's, else the DEM's).",
        ),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


def _scene(manifest_path, dem, dem_datum, footprints, height_field, dsm, bounds, posting_m, required: bool):
    from ..landcover.pipeline import load_scene

    if not (manifest_path or dem):
        if required:
            from ..errors import ConfigError

            raise ConfigError("give the ground: --manifest (AOI, DEM, footprints) or --dem")
        return None
    return load_scene(
        manifest=manifest_path,
        dem=dem,
        dem_datum=dem_datum,
        footprints=footprints,
        dsm=dsm,
        height_field=height_field,
        bounds=tuple(bounds) if bounds else None,
        posting_m=posting_m,
    )


@click.group("landcover")
def landcover() -> None:
    """Land-surface condition over a whole area (e.g. vegetation, debris): classify images, project, integrate.

    train: a pixel classifier from labelled polygons; predict: probability maps per image and on the ground
    grid; integrate: GP regression of the detailed views' probability over every cell, with the coarse image,
    the DEM and the building map as inputs (mean and σ layers; --truth adds the thesis's ablation report).
    """


@landcover.command("train")
@click.option(
    "--labels",
    "labels_path",
    required=True,
    type=click.Path(exists=True, path_type=str),
    help="Label polygons (any OGR layer) with a class attribute; map CRS, or pixel coordinates of the "
    "image when the layer has no CRS.",
)
@click.option("--layer", default=None, help="Layer of a multi-layer label source (default: the first).")
@click.option("--class-field", default=None, help="Class attribute (default: class, label, landcover, ...).")
@click.option("--positive", default=None, help="The condition's class (two classes: its probability is band 2).")
@click.option(
    "--image",
    "images",
    multiple=True,
    required=True,
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    help="Image(s) to learn from (camera found next to each; one sensor per model).",
)
@click.option(
    "--method",
    type=click.Choice(["rf", "logreg", "svm"]),
    default="rf",
    show_default=True,
    help="Random forest (thesis's choice), logistic regression or SVM.",
)
@click.option("--compare", is_flag=True, help="Also cross-validate all three methods, holding out whole polygons.")
@click.option(
    "--height-above-ground",
    is_flag=True,
    help="Add the height above ground as a feature (needs --dsm or footprints with heights).",
)
@click.option(
    "--out",
    "out_path",
    default=None,
    type=click.Path(dir_okay=False, path_type=str),
    help="Model file to write (.joblib; a .json report is written beside it; default: "
    "./geocd_out/landcover/landcover_model.joblib).",
)
@click.option("--seed", type=int, default=0, show_default=True)
@_scene_options
@click.pass_context
def train_cmd(
    ctx,
    labels_path,
    layer,
    class_field,
    positive,
    images,
    method,
    compare,
    height_above_ground,
    out_path,
    seed,
    manifest_path,
    dem,
    dem_datum,
    footprints,
    height_field,
    dsm,
    bounds,
    posting_m,
):
    """Train a pixel classifier from labelled polygons drawn on the images or on the map."""
    from ..landcover.features import FeatureSpec
    from ..landcover.pipeline import train_from_files
    from . import emit_result

    from pathlib import Path

    from ..io.outputs import open_outputs
    from .common import require_inputs, resolve_out_dir, session

    require_inputs(labels_path, *images, what="input")
    if out_path is None:
        out_path = str(resolve_out_dir(None, "landcover", create=False) / "landcover_model.joblib")
    open_outputs(
        None,
        inputs=[labels_path, *images, manifest_path, dem, footprints, dsm],
        files=[out_path, str(Path(out_path).with_suffix(".json"))],
    )
    sess = session(ctx)
    scene = _scene(manifest_path, dem, dem_datum, footprints, height_field, dsm, bounds, posting_m, required=False)
    progress = _progress(ctx, "landcover train")
    try:
        res = train_from_files(
            labels_path,
            list(images),
            out_path,
            layer=layer,
            class_field=class_field,
            positive=positive,
            method=method,
            spec=FeatureSpec(height_above_ground=height_above_ground),
            scene=scene,
            compare=compare,
            seed=seed,
            progress=progress,
        )
    finally:
        _close(progress)
    m = res["model"]
    sess.say(
        f"landcover train ({m.method}): classes {m.classes}, "
        + ", ".join(f"{k} {v}" for k, v in m.report["samples_per_class"].items())
        + " labelled pixels"
    )
    sess.data(classes=m.classes, samples_per_class=m.report["samples_per_class"], comparison=m.report.get("comparison"))
    emit_result(ctx, res["outputs"])


@landcover.command("predict")
@click.option(
    "--model",
    "model_path",
    required=True,
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    help="Model from 'geocd landcover train'.",
)
@click.option(
    "--trust-model",
    is_flag=True,
    help="Load a model file that 'geocd landcover train' did not write for this user (someone else's): "
    "a model is a pickle, and loading it runs any code its author put in it. Only for files from "
    "people you trust.",
)
@click.option(
    "--image",
    "images",
    multiple=True,
    required=True,
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    help="Image(s) to classify.",
)
@click.option("--class", "class_name", default=None, help="Class to project (default: the positive class).")
@click.option(
    "--out",
    "out_dir",
    default=None,
    type=click.Path(file_okay=False, path_type=str),
    help="Output folder (default: ./geocd_out/landcover).",
)
@click.option("--prefix", default="landcover", show_default=True, help="File name prefix.")
@_scene_options
@click.pass_context
def predict_cmd(
    ctx,
    model_path,
    trust_model,
    images,
    class_name,
    out_dir,
    prefix,
    manifest_path,
    dem,
    dem_datum,
    footprints,
    height_field,
    dsm,
    bounds,
    posting_m,
):
    """Probability maps of images (image geometry) and, with a DEM or manifest, on the ground grid: each image
    projected through its camera and the surface (occluded cells stay empty), the views combined by weight."""
    from ..landcover.pipeline import predict_files
    from ..landcover.trust import check_model_file
    from . import emit_result

    from ..io.outputs import open_outputs
    from .common import require_inputs, resolve_out_dir, session

    require_inputs(model_path, *images, what="input")
    sess = session(ctx)
    check_model_file(model_path, trust=trust_model)  # before any output: an untrusted pickle is refused
    out = resolve_out_dir(out_dir, "landcover", create=False)
    open_outputs(
        out, inputs=[model_path, *images, manifest_path, dem, footprints, dsm], products=(f"{prefix}_*",), prefix=prefix
    )
    sess.open_log(out)
    scene = _scene(manifest_path, dem, dem_datum, footprints, height_field, dsm, bounds, posting_m, required=False)
    progress = _progress(ctx, "landcover predict")
    try:
        res = predict_files(
            model_path,
            list(images),
            out,
            scene=scene,
            class_name=class_name,
            prefix=prefix,
            progress=progress,
            trust=trust_model,
        )
    finally:
        _close(progress)
    s = res["summary"]
    line = f"landcover predict: {len(images)} image(s), class {s['class']!r}"
    if "observed_fraction" in s:
        line += f"; {100 * s['observed_fraction']:.1f}% of the grid observed"
    sess.say(line)
    sess.data(**s)
    emit_result(ctx, res["outputs"])


@landcover.command("integrate")
@click.option(
    "--detailed",
    "detailed_path",
    required=True,
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    help="The detailed views' probability on the ground (band 1; NaN = unobserved), e.g. "
    "*_ground.tif of 'geocd landcover predict'.",
)
@click.option(
    "--coarse",
    "coarse_path",
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    default=None,
    help="A coarse full-cover probability on the ground (band 1), e.g. the satellite image's.",
)
@click.option(
    "--inputs",
    default=None,
    help="GP inputs, comma-separated from xy, dem, coarse, buildings (default: all available).",
)
@click.option("--class-name", default="condition", show_default=True, help="Name of the condition (band names).")
@click.option(
    "--kernel",
    type=click.Choice(["additive", "product"]),
    default="additive",
    show_default=True,
    help="additive: ARD kernel over x, y plus one over the other inputs (appearance carries at any "
    "distance); product: one ARD kernel over every input (the thesis's).",
)
@click.option(
    "--n-fit", type=int, default=1000, show_default=True, help="Observed cells for the exact-GP hyperparameter fit."
)
@click.option(
    "--inducing",
    "n_inducing",
    type=int,
    default=400,
    show_default=True,
    help="Inducing points of the sparse prediction.",
)
@click.option("--batch", type=int, default=20000, show_default=True, help="Cells per prediction batch (memory).")
@click.option(
    "--calibrate-folds",
    type=int,
    default=0,
    show_default=True,
    help="Spatial blocks of observed cells held out in turn to scale σ to the detailed views' own "
    "held-out error (band sigma_calibrated); 0 = off. See docs/landcover.md before relying on it.",
)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option(
    "--truth",
    "truth_path",
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    default=None,
    help="Truth raster: adds the ablation report (PR curves, F1 at recall 0.5, σ calibration).",
)
@click.option(
    "--truth-values", default=None, help="Comma-separated truth codes that mean the condition (default: nonzero)."
)
@click.option(
    "--exclude-labels",
    "exclude_path",
    type=click.Path(exists=True, path_type=str),
    default=None,
    help="Training label layer: its cells are left out of the ablation scores.",
)
@click.option(
    "--out",
    "out_dir",
    default=None,
    type=click.Path(file_okay=False, path_type=str),
    help="Output folder (default: ./geocd_out/landcover).",
)
@click.option("--prefix", default="landcover", show_default=True, help="File name prefix.")
@_scene_options
@click.pass_context
def integrate_cmd(
    ctx,
    detailed_path,
    coarse_path,
    inputs,
    class_name,
    kernel,
    n_fit,
    n_inducing,
    batch,
    calibrate_folds,
    seed,
    truth_path,
    truth_values,
    exclude_path,
    out_dir,
    prefix,
    manifest_path,
    dem,
    dem_datum,
    footprints,
    height_field,
    dsm,
    bounds,
    posting_m,
):
    """GP integration over every cell: predictive mean and σ (Cloud-Optimized GeoTIFFs)."""
    from ..landcover.gp import GPParams
    from ..landcover.pipeline import integrate_files
    from . import emit_result

    from ..io.outputs import open_outputs
    from .common import require_inputs, resolve_out_dir, session

    require_inputs(detailed_path, coarse_path, truth_path, exclude_path, what="input")
    out = resolve_out_dir(out_dir, "landcover", create=False)
    scene = _scene(manifest_path, dem, dem_datum, footprints, height_field, dsm, bounds, posting_m, required=True)
    open_outputs(
        out,
        inputs=[detailed_path, coarse_path, truth_path, exclude_path, manifest_path, dem, footprints, dsm],
        products=(f"{prefix}_*",),
        prefix=prefix,
    )
    sess = session(ctx)
    sess.open_log(out)
    use = tuple(s.strip() for s in inputs.split(",") if s.strip()) if inputs else None
    tv = [float(s) for s in truth_values.split(",") if s.strip()] if truth_values else None
    params = GPParams(
        n_fit=n_fit, n_inducing=n_inducing, batch=batch, seed=seed, kernel=kernel, calibrate_folds=calibrate_folds
    )
    progress = _progress(ctx, "landcover integrate")
    try:
        res = integrate_files(
            detailed_path,
            scene,
            out,
            coarse_path=coarse_path,
            use=use,
            params=params,
            class_name=class_name,
            truth_path=truth_path,
            truth_values=tv,
            exclude_path=exclude_path,
            prefix=prefix,
            progress=progress,
        )
    finally:
        _close(progress)
    s = res["summary"]
    sess.say(
        f"landcover integrate: {s['observed_cells']} of {s['cells']} cells observed; GP inputs {s['inputs']}, "
        f"{s['inducing_points']} inducing points, {s['seconds']:.1f} s"
    )
    if "ablation" in s:
        for k, v in s["ablation"].items():
            sess.say(f"  F1 at recall 0.5, {k}: {v}")
    sess.data(**{k: v for k, v in s.items() if k != "hyper"})
    emit_result(ctx, res["outputs"])
