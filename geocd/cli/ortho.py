"""``geocd ortho``: true orthoimages on the AOI grid (one image with a DSM, or every image of a manifest)."""

from __future__ import annotations

from pathlib import Path

import click

from ..io.outputs import geotiff_tag_startswith, is_qgis_style


def _is_geocd_ortho(p: Path) -> bool:
    """Whether ``p`` is a GeoTIFF geocd ortho wrote (its ``method`` tag)."""
    return geotiff_tag_startswith(p, "method", "geocd ortho")


def _is_manifest(p: Path) -> bool:
    return p.is_dir() or p.suffix.lower() in (".yaml", ".yml", ".json")


def _dsm_arg(values: tuple[str, ...]):
    """--dsm PATH (every epoch) or --dsm EPOCH=PATH (repeatable)."""
    from ..errors import ConfigError

    if not values:
        return None
    per = {}
    plain = []
    for v in values:
        if "=" in v and not Path(v).exists():
            k, p = v.split("=", 1)
            per[k] = p
        else:
            plain.append(v)
    if plain and (per or len(plain) > 1):
        raise ConfigError("give either one --dsm PATH for every epoch, or --dsm EPOCH=PATH per epoch")
    return plain[0] if plain else per


@click.command("ortho")
@click.argument("source", type=click.Path(path_type=str))
@click.option(
    "--dsm",
    "dsm",
    multiple=True,
    metavar="[EPOCH=]PATH",
    help="Surface model (any CRS and datum GDAL reads; ellipsoidal or with its vertical CRS). One PATH for "
    "every epoch, or EPOCH=PATH per epoch. Default for a manifest: geocd stereo of the epoch.",
)
@click.option(
    "--dsm-source",
    type=click.Choice(["auto", "stereo", "dem"]),
    default="auto",
    show_default=True,
    help="Manifest: where each epoch's DSM comes from (auto = --dsm, else geocd stereo when the epoch has "
    "two images, else the manifest's DEM: a classic, not a true ortho).",
)
@click.option("--epoch", "epochs", multiple=True, help="Manifest: epoch to do (repeatable; default all).")
@click.option("--image", "images", multiple=True, help="Manifest: image name to do (repeatable; default all).")
@click.option(
    "--camera",
    "camera_path",
    type=click.Path(path_type=str),
    default=None,
    help="Single image: camera file (default: RPC tags, RPC sidecar or frame sidecar of the image).",
)
@click.option(
    "--out",
    "out",
    type=click.Path(path_type=str),
    default=None,
    help="Single image: output GeoTIFF (default ./geocd_out/IMAGE/IMAGE_ortho.tif). Manifest: output folder "
    "(default the manifest's 'output:', else ./geocd_out/<scene name>); orthos go to "
    "OUT/ortho/EPOCH/NAME.tif.",
)
@click.option(
    "--posting",
    "posting_m",
    type=float,
    default=None,
    help="Grid posting in metres (manifest: default the manifest's aoi, else the images' GSD; single image: "
    "default the DSM's grid).",
)
@click.option(
    "--resampling",
    type=click.Choice(["bilinear", "nearest"]),
    default="bilinear",
    show_default=True,
    help="nearest for class labels.",
)
@click.option(
    "--occlusion/--no-occlusion",
    default=True,
    show_default=True,
    help="True ortho: cells hidden from the camera by the DSM are nodata (--no-occlusion: classic ortho).",
)
@click.option(
    "--occlusion-tol",
    "occlusion_tol_m",
    type=float,
    default=None,
    help="Metres the DSM must rise above a line of sight to hide a cell (default: max(0.5, 3 × the DSM's "
    "local noise)).",
)
@click.option(
    "--antialias/--no-antialias",
    default=True,
    show_default=True,
    help="Low-pass the image first when a grid cell spans 1.5 image pixels or more.",
)
@click.option(
    "--view-bands", is_flag=True, help="Also write NAME_view.tif: view zenith/azimuth, incidence, px per cell."
)
@click.option("--no-overwrite", is_flag=True, help="Fail instead of replacing existing outputs.")
@click.option(
    "--overwrite",
    is_flag=True,
    help="Single image: replace an existing --out file even when geocd did not write it (by default only "
    "an earlier geocd ortho is replaced).",
)
@click.pass_context
def ortho(
    ctx: click.Context,
    source: str,
    dsm,
    dsm_source: str,
    epochs,
    images,
    camera_path,
    out,
    posting_m,
    resampling: str,
    occlusion: bool,
    occlusion_tol_m,
    antialias: bool,
    view_bands: bool,
    no_overwrite: bool,
    overwrite: bool,
) -> None:
    """Orthorectify SOURCE onto the AOI grid with a DSM: a true ortho, where a cell the camera cannot see is
    nodata (GDAL mask) instead of receiving the occluding roof's pixels.

    SOURCE is a manifest (every image of its epochs, RPC and frame cameras alike) or one image (then --dsm is
    required and its grid is the output grid unless --posting is given). Writes per image a COG in the image's
    own dtype and bands, NAME_status.tif (seen / occluded / outside / no height) and QGIS styles.
    """
    from ..errors import ConfigError, InputFileNotFoundError
    from ..ortho import OrthoParams
    from . import emit_result, make_progress
    from .common import default_out_dir, session

    sess = session(ctx)
    params = OrthoParams(
        resampling=resampling, occlusion=occlusion, occlusion_tol_m=occlusion_tol_m, antialias=antialias
    )
    src = Path(source)
    if not src.exists():
        raise InputFileNotFoundError(f"{src} does not exist; give a manifest, a scene folder or an image")
    if overwrite and no_overwrite:
        raise ConfigError("--overwrite and --no-overwrite contradict each other; give one")
    dsm_spec = _dsm_arg(tuple(dsm))
    progress = make_progress(ctx, "ortho")
    try:
        if _is_manifest(src):
            from ..io.manifest import load_manifest
            from ..io.outputs import open_outputs
            from ..ortho.pipeline import run_ortho

            src = load_manifest(src)
            dsm_files = [v for v in (dsm_spec.values() if isinstance(dsm_spec, dict) else [dsm_spec]) if v]
            open_outputs(
                out or src.output_dir(), inputs=[*src.input_paths(), *dsm_files], products=("ortho/*", "stereo/*")
            )

            res = run_ortho(
                src,
                epochs=list(epochs) or None,
                images=list(images) or None,
                out_dir=out,
                dsm=dsm_spec,
                dsm_source=dsm_source,
                posting_m=posting_m,
                params=params,
                view_bands=view_bands,
                overwrite=not no_overwrite,
                progress=progress,
            )
            outputs = {k: v for k, v in res["outputs"].items()}
            for k, f in res["fractions"].items():
                sess.say(
                    f"{k}: seen {f['seen'] + f['seen_filled_height']:.1%}, occluded {f['occluded']:.1%}, "
                    f"outside {f['outside_image']:.1%}"
                )
        else:
            if not isinstance(dsm_spec, str):
                raise ConfigError("orthorectifying one image needs one DSM: --dsm PATH")
            from ..io.outputs import open_outputs, refuse_foreign_files

            dst = Path(out) if out else default_out_dir(src.stem) / f"{src.stem}_ortho.tif"
            open_outputs(
                None,
                files=[
                    dst.parent / f"{dst.stem}{s}" for s in (".tif", ".qml", "_status.tif", "_status.qml", "_view.tif")
                ],
                inputs=[src, camera_path, dsm_spec],
            )
            rasters = [dst, *(dst.parent / f"{dst.stem}{s}" for s in (".tif", "_status.tif", "_view.tif"))]
            refuse_foreign_files(rasters, _is_geocd_ortho, what="a geocd ortho GeoTIFF", force=overwrite)
            refuse_foreign_files(
                [dst.parent / f"{dst.stem}{s}" for s in (".qml", "_status.qml")],
                is_qgis_style,
                what="a QGIS style",
                force=overwrite,
            )
            import numpy as np

            from ..geodesy import AOIGrid
            from ..io.cameras import load_camera
            from ..io.raster import read_dem
            from ..ortho import fill_dsm_holes
            from ..ortho.pipeline import ortho_image

            d = read_dem(dsm_spec)
            grid = d.grid
            if posting_m is not None:
                grid = AOIGrid.from_bounds(*grid.bounds, posting_m, grid.crs)
                d = read_dem(dsm_spec, grid=grid)
            h = d.to_ellipsoidal().height_m
            filled, hole = fill_dsm_holes(h)
            cam = load_camera(src, camera_path)
            dst.parent.mkdir(parents=True, exist_ok=True)
            progress(0.1, f"ortho {src.name}")
            paths, r = ortho_image(
                src,
                cam,
                grid,
                filled,
                dst,
                params=params,
                dsm_filled=hole,
                view_bands=view_bands,
                overwrite=not no_overwrite,
                tags={"dsm": str(dsm_spec)},
            )
            progress(1.0, "ortho done")
            outputs = paths
            f = r.fractions()
            sess.say(
                f"seen {f['seen'] + f['seen_filled_height']:.1%}, occluded {f['occluded']:.1%}, "
                f"outside {f['outside_image']:.1%}; DSM holes filled: {float(np.mean(hole)):.1%}"
            )
    finally:
        if hasattr(progress, "close"):
            progress.close()
    emit_result(ctx, outputs)
