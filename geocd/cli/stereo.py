"""``geocd stereo MANIFEST`` or ``geocd stereo A.tif B.tif``: pair-DEMs (z, score, g, valid, ...) for every
image pair of an epoch."""

from __future__ import annotations

from pathlib import Path

import click

from .common import dask_options

INPUT_HELP = (
    "INPUTS: a scene manifest (scene.yaml) or a folder of images, or two or more images of one date "
    "(GeoTIFF/NITF with RPC tags or an RPC/frame camera sidecar): `geocd stereo a.tif b.tif --out dsm/`."
)


def _is_image(path: str) -> bool:
    from ..io.manifest import IMAGE_SUFFIXES

    return Path(path).suffix.lower() in IMAGE_SUFFIXES


def scene_from_inputs(inputs: tuple[str, ...]):
    """A manifest from the positional inputs: one manifest/folder, or 2+ images (one epoch named ``pair``)."""
    from ..errors import ConfigError
    from ..io.manifest import Epoch, ImageSpec, Manifest, load_manifest

    if len(inputs) == 1:
        p = inputs[0]
        if Path(p).is_file() and _is_image(p):
            raise ConfigError(
                f"{p} is one image; stereo needs two or more: `geocd stereo {p} OTHER.tif --out DIR`, "
                "or a scene manifest (scene.yaml) or a folder of images"
            )
        return load_manifest(p)
    not_images = [p for p in inputs if Path(p).is_dir() or not _is_image(p)]
    if not_images:
        raise ConfigError(
            f"give one scene manifest or folder, or two or more images; {not_images[0]} is not an image "
            "(.tif, .ntf, .jp2, ...)"
        )
    names = [Path(p).stem for p in inputs]
    if len(set(names)) != len(names):
        names = [f"{i + 1}_{n}" for i, n in enumerate(names)]
    ims = tuple(ImageSpec(Path(p).resolve(), None, n) for p, n in zip(inputs, names))
    return Manifest(
        path=None, name="__".join(names[:2]) + ("__etc" if len(names) > 2 else ""), epochs=(Epoch("pair", None, ims),)
    )


@click.command(
    "stereo",
    help="Match every image pair of each epoch in object space (RPC and frame cameras alike)."
    "\n\n" + INPUT_HELP + "\n\nFor each pair, writes a Cloud-Optimized GeoTIFF on the AOI grid with bands z "
    "(ellipsoidal m), score (MDL bits/pixel, lower = better), g (px of disparity per m), valid, ncc, ssd "
    "and flags, to OUT/stereo/EPOCH/A__B.tif (the epoch of images given directly is `pair`).",
)
@click.argument("inputs", nargs=-1, required=True, type=click.Path(path_type=str))
@click.option(
    "--epoch", "epochs", multiple=True, help="Epoch to process (repeatable; default: every epoch with 2+ images)."
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(path_type=str),
    default=None,
    help="Output folder (default: the manifest's 'output:' if it names one, else ./geocd_out/<name>). "
    "Pair-DEMs go to OUT/stereo/EPOCH/A__B.tif.",
)
@click.option(
    "--posting",
    "posting_m",
    type=float,
    default=None,
    help="Grid posting in metres (default: manifest aoi, else the images' GSD).",
)
@click.option("--window", type=int, default=None, help="Matching window side in cells (odd, default 7).")
@click.option(
    "--height-range",
    nargs=2,
    type=float,
    default=None,
    metavar="MIN MAX",
    help="Ellipsoidal height search range in metres (default: prior DEM ± margin, else the cameras' range).",
)
@click.option("--dem-margin", type=float, default=None, help="Search margin around the prior DEM, metres (default 30).")
@click.option(
    "--score",
    type=click.Choice(["mdl", "ncc", "ssd"]),
    default=None,
    help="What the score band holds (default mdl; ncc and ssd bands are written anyway).",
)
@click.option(
    "--score-subwindow",
    type=int,
    default=None,
    help="MDL score = the worst of the sub-windows of this side (cells, odd) tiling the matching window "
    "(default 3; a value ≥ --window scores the whole window).",
)
@click.option(
    "--surface-median",
    type=int,
    default=None,
    help="Median of the valid heights over this many cells (odd) after the tests; default: the matching "
    "window; 1 = off.",
)
@click.option(
    "--isolation-min-cells",
    type=int,
    default=None,
    help="A valid height whose surface patch (neighbours within one pixel of disparity) holds fewer cells "
    "is invalid (flag not_unique); default: one matching window (window² cells); 1 = off.",
)
@click.option(
    "--no-fill",
    is_flag=True,
    help="Leave holes narrower than the matching window empty (default: z holds interpolated heights "
    "there, flagged 'filled' and not valid).",
)
@click.option(
    "--tile-size",
    type=int,
    default=None,
    help="Tile side in cells: with --tiled, the Dask tile [1024]; otherwise the in-memory plane sweep's "
    "tile (memory bound) [256].",
)
@click.option(
    "--tiled",
    is_flag=True,
    help="Match tile by tile on Dask (whole scenes: bounded memory, resumable after a kill: run the same "
    "command again). Implied by --scheduler, --workers or --memory-limit.",
)
@dask_options
@click.option("--no-overwrite", is_flag=True, help="Fail instead of replacing existing pair-DEMs.")
@click.pass_context
def stereo(
    ctx: click.Context,
    inputs: tuple[str, ...],
    epochs: tuple[str, ...],
    out_dir: str | None,
    posting_m: float | None,
    window: int | None,
    height_range,
    dem_margin: float | None,
    score: str | None,
    score_subwindow: int | None,
    surface_median: int | None,
    isolation_min_cells: int | None,
    no_fill: bool,
    tile_size: int | None,
    tiled: bool,
    scheduler: str | None,
    workers: int | None,
    memory_limit: str | None,
    no_overwrite: bool,
) -> None:
    from .common import require_inputs, resolve_out_dir, session

    require_inputs(*inputs)
    tiled = tiled or any(v is not None for v in (scheduler, workers, memory_limit))
    if tiled and no_overwrite:
        from ..errors import ConfigError

        raise ConfigError(
            "--no-overwrite is for untiled runs: a tiled run resumes into its output folder and replaces "
            "its pair-DEMs when done; choose a new --out to keep earlier ones"
        )
    m = scene_from_inputs(inputs)
    out = resolve_out_dir(out_dir if out_dir is not None else m.output, m.name, create=False)
    from ..io.outputs import open_outputs
    from ..stereo import StereoParams
    from ..stereo.pipeline import run_stereo
    from . import emit_result, make_progress

    open_outputs(out, inputs=m.input_paths(), products=tuple(f"stereo/{e}/*" for e in epochs) or ("stereo/*",))
    sess = session(ctx)
    sess.open_log(out)

    kw = {}
    if window is not None:
        kw["window"] = window
    if height_range:
        kw["height_range_m"] = tuple(height_range)
    if dem_margin is not None:
        kw["dem_margin_m"] = dem_margin
    if score is not None:
        kw["score"] = score
    if score_subwindow is not None:
        kw["score_subwindow"] = score_subwindow
    if surface_median is not None:
        kw["surface_median"] = surface_median
    if isolation_min_cells is not None:
        kw["isolation_min_cells"] = isolation_min_cells
    if no_fill:
        kw["fill_holes"] = False
    if tile_size is not None and not tiled:
        kw["tile_size"] = tile_size
    params = StereoParams(**kw)
    progress = make_progress(ctx, "stereo")
    try:
        if tiled:
            res = _stereo_tiled(
                m,
                epochs,
                out,
                params,
                posting_m,
                progress,
                {
                    k: v
                    for k, v in (
                        ("scheduler", scheduler),
                        ("tile_size", tile_size),
                        ("n_workers", workers),
                        ("memory_limit", memory_limit),
                    )
                    if v is not None
                },
            )
            sess.say(
                f"tiled stereo: margins {res['margins']} cells; completeness "
                + ", ".join(f"{k} {v:.3f}" for k, v in res["completeness"].items())
            )
        else:
            res = run_stereo(
                m,
                epochs=list(epochs) or None,
                out_dir=out,
                params=params,
                posting_m=posting_m,
                overwrite=not no_overwrite,
                progress=progress,
            )
    finally:
        progress.close()
    g = res["grid"]
    sess.say(f"{len(res['outputs'])} pair-DEM(s) on a {g.width}x{g.height} grid at {g.posting_m:g} m ({g.crs})")
    sess.data(
        grid=g.to_dict(),
        pairs=sorted(res["outputs"]),
        pair_warnings=list(res.get("warnings", [])),
        skipped_pairs=list(res.get("notes", [])),
    )
    emit_result(ctx, res["outputs"])


def _stereo_tiled(m, epochs, out, params, posting_m, progress, tiling_opts: dict):
    """The tiled door: the manifest's cross-image orientation as the untiled run applies it, then
    :func:`geocd.stereo.tiled.run_stereo_tiled`."""
    from ..tiling.params import TilingParams
    from ..io.atomic import protect_inputs
    from ..orientation import orient_manifest
    from ..stereo.tiled import run_stereo_tiled

    m, _ = orient_manifest(m, out_dir=out, stereo_params=params)
    protect_inputs(*[im.path for e in m.epochs for im in e.images])
    return run_stereo_tiled(
        m,
        out_dir=out,
        epochs=list(epochs) or None,
        params=params,
        posting_m=posting_m,
        tiling=TilingParams(**tiling_opts),
        progress=progress,
    )
