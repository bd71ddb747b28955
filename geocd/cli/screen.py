"""``geocd screen``: fast 2-D change screening with grid features and superpixels (Sakurada's thesis, ch. 4)."""

from __future__ import annotations

from pathlib import Path

import click

from .common import check_confidence, pixel_size_option


def _is_manifest(p: Path) -> bool:
    return p.is_dir() or p.suffix.lower() in (".yaml", ".yml", ".json")


def feature_options(f):
    """Options choosing the grid feature and the screen's steps (shared with ``geocd run --screen``)."""
    opts = [
        click.option(
            "--feature",
            type=click.Choice(["randbank", "daisy", "patch", "cnn"]),
            default="patch",
            show_default=True,
            help="Grid feature: patch (grey 16×16 local patch), daisy (multi-scale dense DAISY, the "
            "thesis's Dense-SIFT baseline), randbank (seeded random-filter bank), cnn (a CNN pooling "
            "layer from --weights). Default: the best F1 without pretrained weights (docs/screen.md).",
        ),
        click.option(
            "--cell",
            "cell_px",
            type=int,
            default=16,
            show_default=True,
            help="Grid cell in image pixels (patch, daisy, randbank; a CNN layer's stride sets its own).",
        ),
        click.option(
            "--backbone",
            default=None,
            help="cnn: vgg11/13/16/19 (or _bn), vgg (layers read from the file), resnet18/34/50/101, resnet, "
            "efficientnet_lite0..4.",
        ),
        click.option(
            "--weights",
            type=click.Path(exists=True, dir_okay=False, path_type=str),
            default=None,
            help="cnn: weights file (.npz or a PyTorch .pt/.pth state_dict, read without PyTorch when it is "
            "not installed); never downloaded.",
        ),
        click.option(
            "--layer",
            default=None,
            help="cnn: pool1..pool5 (VGG, default pool5), pool/layer1..layer4 "
            "(ResNet, default layer3), stage1..stage7/head (EfficientNet-Lite, "
            "default stage5).",
        ),
        click.option(
            "--superpixels",
            type=click.Choice(["felzenszwalb", "slic", "none"]),
            default="felzenszwalb",
            show_default=True,
            help="Superpixel refinement (Felzenszwalb as in the thesis, SLIC, or none).",
        ),
        click.option(
            "--segment", "segment_m", type=float, default=3.0, show_default=True, help="Typical superpixel size (m)."
        ),
        click.option(
            "--vegetation",
            type=click.Choice(["both", "either", "off"]),
            default="both",
            show_default=True,
            help="Set aside vegetation seen in both dates (NDVI or excess green; needs colour or nir).",
        ),
        click.option(
            "--shadow",
            type=click.Choice(["both", "either", "off"]),
            default="both",
            show_default=True,
            help="Set aside cast shadows seen in both dates.",
        ),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


def screen_params(feature, cell_px, backbone, weights, layer, superpixels, segment_m, vegetation, shadow):
    from ..screen import FeatureSpec, ScreenParams

    return ScreenParams(
        feature=FeatureSpec(kind=feature, cell_px=cell_px, backbone=backbone, weights=weights, layer=layer),
        superpixels=superpixels,
        segment_m=segment_m,
        vegetation=vegetation,
        shadow=shadow,
    )


@click.command("screen")
@click.argument("sources", nargs=-1, required=True, type=click.Path(path_type=str))
@feature_options
@click.option(
    "--threshold",
    type=float,
    default=None,
    help="Fixed dissimilarity threshold (default: from the no-change pair at --confidence, or a labelled pair).",
)
@click.option(
    "--confidence",
    type=float,
    default=99.0,
    show_default=True,
    callback=check_confidence,
    help="Percent: a cell is changed when its dissimilarity exceeds this percentile of the no-change pair's.",
)
@click.option(
    "--nochange",
    multiple=True,
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    metavar="RASTER",
    help="Give twice: a pair of rasters known to hold no change (e.g. two views of one "
    "date) that sets the threshold and the confidence.",
)
@click.option(
    "--labelled",
    nargs=3,
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    default=None,
    metavar="A B TRUTH",
    help="A labelled pair (another place or date): the threshold of its best F1.",
)
@click.option(
    "--image-a",
    default=None,
    help="Manifest: the image of epoch A to compare, by name (with --image-b; default: the closest views of the "
    "same sensor kind).",
)
@click.option("--image-b", default=None, help="Manifest: the image of epoch B to compare, by name (with --image-a).")
@click.option(
    "--dsm",
    "dsm",
    multiple=True,
    metavar="EPOCH=PATH",
    help="Manifest: a DSM per epoch (true orthos); default: the views on the terrain DEM.",
)
@click.option("--epoch-a", default=None, help="Manifest: earlier epoch (default: first).")
@click.option("--epoch-b", default=None, help="Manifest: later epoch (default: last).")
@click.option("--tile-size", type=int, default=1024, show_default=True, help="Tile side (cells).")
@click.option(
    "--scheduler",
    default=None,
    metavar="SCHEDULER",
    help="Tiled runs: sync | threads | processes | auto (a local Dask cluster sized to the machine, the default; "
    "this process when there is one tile) | ADDRESS of a running dask.distributed scheduler (tcp://host:8786).",
)
@click.option(
    "--out",
    "out_dir",
    default=None,
    type=click.Path(file_okay=False, path_type=str),
    help="Output folder (default: ./geocd_out/<scene or image A>).",
)
@pixel_size_option("Two rasters A B")
@click.option("--no-overwrite", is_flag=True, help="Fail instead of replacing existing outputs.")
@click.pass_context
def screen(
    ctx,
    sources,
    feature,
    cell_px,
    backbone,
    weights,
    layer,
    superpixels,
    segment_m,
    vegetation,
    shadow,
    threshold,
    confidence,
    nochange,
    labelled,
    image_a,
    image_b,
    dsm,
    epoch_a,
    epoch_b,
    tile_size,
    scheduler,
    out_dir,
    pixel_size,
    no_overwrite,
):
    """Fast 2-D change screening: compare two images cell by cell with grid features, refine with superpixels.

    SOURCES is a manifest (its views on the AOI grid; the threshold from a within-epoch pair of views) or two
    georeferenced rasters A B (orthoimages; B is resampled onto A's grid; different band counts are compared in
    grey), or two plain images of one size with --pixel-size. Writes screen_dissimilarity.tif,
    screen_change_mask.tif, screen_changes.gpkg (the shared changes layer) and screen_summary.json.
    """
    from ..errors import ConfigError
    from ..io.plain import on_local_grid
    from . import emit_result, make_progress
    from .common import require_inputs, resolve_out_dir, session

    require_inputs(*sources, weights, what="input")
    scheduler = scheduler or "auto"
    if (image_a is None) != (image_b is None):
        raise ConfigError("give both --image-a and --image-b (names of the manifest's images), or neither")
    pair = (image_a, image_b) if image_a is not None else None
    if nochange and len(nochange) != 2:
        raise ConfigError(f"--nochange is given twice (two rasters of one date), got {len(nochange)}")
    sess = session(ctx)
    params = screen_params(feature, cell_px, backbone, weights, layer, superpixels, segment_m, vegetation, shadow)
    fa_pct = 100.0 - float(confidence)
    progress = make_progress(ctx, "screen")
    from ..io.outputs import open_outputs

    try:
        if len(sources) == 1 and _is_manifest(Path(sources[0])):
            if pixel_size is not None:
                raise ConfigError("--pixel-size is for two plain images A B; a manifest's views have cameras")
            from ..io.manifest import load_manifest
            from ..screen.pipeline import PRODUCTS_GLOBS, run_screen_manifest

            if nochange or labelled:
                raise ConfigError(
                    "--nochange and --labelled are for two rasters; a manifest takes its no-change "
                    "pair from the views of one epoch"
                )
            m = load_manifest(sources[0])
            out = resolve_out_dir(out_dir, m.name, create=False) if out_dir else m.output_dir()
            dsm_map = {}
            for v in dsm:
                if "=" not in v:
                    raise ConfigError(f"--dsm takes EPOCH=PATH, got {v!r}")
                k, p = v.split("=", 1)
                require_inputs(p, what="DSM")
                dsm_map[k] = p
            open_outputs(out, inputs=[*m.input_paths(), *dsm_map.values(), weights], products=PRODUCTS_GLOBS)
            sess.open_log(out)
            res = run_screen_manifest(
                m,
                out=out,
                params=params,
                threshold=threshold,
                false_alarm_pct=fa_pct,
                pair=tuple(pair) if pair else None,
                dsm=dsm_map or None,
                epoch_a=epoch_a,
                epoch_b=epoch_b,
                tile_size=tile_size,
                scheduler=scheduler,
                overwrite=not no_overwrite,
                progress=progress,
            )
            sess.say(
                f"screen {m.name}: {res['pair'][0]} → {res['pair'][1]}"
                + (
                    f", no-change pair {res['nochange_pair'][0]}/{res['nochange_pair'][1]}"
                    if res["nochange_pair"]
                    else ""
                )
            )
        elif len(sources) == 2:
            from ..screen.cnn import load_weights
            from ..screen.pipeline import PRODUCTS_GLOBS, RasterImage, run_screen_files

            if pair or dsm:
                raise ConfigError("--image-a/--image-b and --dsm are for a manifest")
            with on_local_grid([sources, nochange or (), labelled or ()], pixel_size) as rasters:
                # the inputs' own problems first (headers and weights: cheap), then the missing rule, then the work
                for r in rasters[0]:
                    RasterImage.open(r)
                if weights is not None:
                    load_weights(weights)
                if threshold is None and not nochange and not labelled:
                    raise ConfigError(
                        "the screen of two rasters needs a threshold rule: a no-change pair (--nochange A2 B2), a "
                        "labelled pair (--labelled A B TRUTH) or --threshold VALUE"
                    )
                out = resolve_out_dir(out_dir, Path(sources[0]).stem, create=False)
                open_outputs(
                    out, inputs=[*sources, *(nochange or ()), *(labelled or ()), weights], products=PRODUCTS_GLOBS
                )
                sess.open_log(out)
                if pixel_size is not None:
                    sess.note(f"plain images on a local grid of {pixel_size:g} m pixels (no map CRS)")
                res = run_screen_files(
                    str(rasters[0][0]),
                    str(rasters[0][1]),
                    out=out,
                    params=params,
                    threshold=threshold,
                    nochange=tuple(map(str, rasters[1])) if nochange else None,
                    labelled=tuple(map(str, rasters[2])) if labelled else None,
                    false_alarm_pct=fa_pct,
                    tile_size=tile_size,
                    scheduler=scheduler,
                    overwrite=not no_overwrite,
                    progress=progress,
                )
        else:
            raise ConfigError("give a manifest, or two rasters A B")
    finally:
        if hasattr(progress, "close"):
            progress.close()
    sr = res["run"]
    import numpy as np

    ok = sr.valid & np.isfinite(sr.dissimilarity)
    frac = float((sr.dissimilarity[ok] > res["threshold"]).mean()) if ok.any() else 0.0
    sess.say(
        f"threshold {res['threshold']:.3f} ({res['rule']}); changed {100 * frac:.2f} % of the observed cells; "
        f"{sr.n_tiles} tile(s), {sr.wall_s:.1f} s"
    )
    for n in sr.notes:
        sess.note(n)
    sess.data(
        threshold=res["threshold"],
        threshold_rule=res["rule"],
        changed_fraction=round(frac, 5),
        null=res["null"].to_dict() if res["null"] is not None else None,
        seconds=round(sr.wall_s, 2),
    )
    emit_result(ctx, res["outputs"])
