"""``geocd stereo MANIFEST``: pair-DEMs (z, score, g, valid, ...) for every image pair of an epoch."""

from __future__ import annotations

import click


@click.command("stereo")
@click.argument("manifest", type=click.Path(path_type=str))
@click.option("--epoch", "epochs", multiple=True, help="Epoch to process (repeatable; default: every epoch with 2+ images).")
@click.option("--out", "out_dir", type=click.Path(path_type=str), default=None,
              help="Output folder (default: the manifest's output). Pair-DEMs go to OUT/stereo/EPOCH/A__B.tif.")
@click.option("--posting", "posting_m", type=float, default=None, help="Grid posting in metres (default: manifest aoi, else the images' GSD).")
@click.option("--window", type=int, default=None, help="Matching window side in cells (odd, default 7).")
@click.option("--height-range", nargs=2, type=float, default=None, metavar="MIN MAX",
              help="Ellipsoidal height search range in metres (default: prior DEM ± margin, else the cameras' range).")
@click.option("--dem-margin", type=float, default=None, help="Search margin around the prior DEM, metres (default 30).")
@click.option("--score", type=click.Choice(["mdl", "ncc", "ssd"]), default=None,
              help="What the score band holds (default mdl; ncc and ssd bands are written anyway).")
@click.option("--score-subwindow", type=int, default=None,
              help="MDL score = the worst of the sub-windows of this side (cells, odd) tiling the matching window "
                   "(default 3; a value ≥ --window scores the whole window).")
@click.option("--tile-size", type=int, default=None, help="Tile side in cells (memory bound; default 256).")
@click.option("--no-overwrite", is_flag=True, help="Fail instead of replacing existing pair-DEMs.")
@click.pass_context
def stereo(ctx: click.Context, manifest: str, epochs: tuple[str, ...], out_dir: str | None, posting_m: float | None,
           window: int | None, height_range, dem_margin: float | None, score: str | None,
           score_subwindow: int | None, tile_size: int | None, no_overwrite: bool) -> None:
    """Match every image pair of each epoch of MANIFEST in object space (RPC and frame cameras alike).

    For each pair, writes a Cloud-Optimized GeoTIFF on the AOI grid with bands z (ellipsoidal m), score
    (MDL bits/pixel, lower = better), g (px of disparity per m), valid, ncc, ssd and flags.
    """
    from ..io.manifest import load_manifest
    from ..io.outputs import open_outputs
    from ..stereo import StereoParams
    from ..stereo.pipeline import run_stereo
    from . import emit_result, make_progress

    manifest = load_manifest(manifest)
    open_outputs(out_dir or manifest.output, inputs=manifest.input_paths(),
                 products=tuple(f"stereo/{e}/*" for e in epochs) or ("stereo/*",))

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
    if tile_size is not None:
        kw["tile_size"] = tile_size
    params = StereoParams(**kw)
    progress = make_progress(ctx, "stereo")
    try:
        res = run_stereo(manifest, epochs=list(epochs) or None, out_dir=out_dir, params=params, posting_m=posting_m,
                         overwrite=not no_overwrite, progress=progress)
    finally:
        if hasattr(progress, "close"):
            progress.close()
    emit_result(ctx, res["outputs"])
