"""``geocd volume update|detect|render``: the variable-resolution probabilistic volume model."""

from __future__ import annotations

from pathlib import Path

import click


def _progress(ctx, stage):
    from . import make_progress

    return make_progress(ctx, stage)


def _close(p):
    if hasattr(p, "close"):
        p.close()


def _say(ctx, msg: str) -> None:
    """A note on stderr (and in the log) while the command runs."""
    from .common import session

    session(ctx).note(msg)


@click.group("volume")
def volume() -> None:
    """Octree occlusion-density + appearance model (Crispell et al.): learn from images, detect change, render."""


@volume.command("update")
@click.argument("model_dir", type=click.Path(path_type=str))
@click.option(
    "--manifest",
    "manifest_path",
    type=click.Path(exists=True, path_type=str),
    default=None,
    help="Scene manifest (scene.yaml or its folder): its AOI/DEM define a new model, its images feed it.",
)
@click.option("--epoch", "epochs", multiple=True, help="Epoch(s) of the manifest to learn from (default: the first).")
@click.option(
    "--image",
    "images",
    multiple=True,
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    help="Image(s) to learn from instead of the manifest's (camera found next to each image).",
)
@click.option("--exclude", multiple=True, help="Image names to leave out (e.g. a held-out view).")
@click.option("--passes", type=int, default=5, show_default=True, help="Passes over the images (random order).")
@click.option(
    "--finest-cell",
    "finest_cell_m",
    type=float,
    default=0.5,
    show_default=True,
    help="Finest octree cell edge, metres (new models).",
)
@click.option("--max-depth", type=int, default=3, show_default=True, help="Octree levels below a block (new models).")
@click.option(
    "--init-depth", type=int, default=1, show_default=True, help="Initial refinement level of every block (new models)."
)
@click.option(
    "--above",
    "above_m",
    type=float,
    default=30.0,
    show_default=True,
    help="Volume top above the DEM's highest point, metres (new models).",
)
@click.option("--fixed-grid", is_flag=True, help="New model as a fixed grid at the finest level (no refinement).")
@click.option(
    "--no-dem-prior",
    is_flag=True,
    help="New model: do not seed the occlusion density from the manifest's DEM (ground band occupied, high air empty).",
)
@click.option(
    "--roofs-from-footprints",
    "use_footprints",
    is_flag=True,
    help="New model: put the DEM prior's surface band at "
    "roof heights swept from the manifest's footprints over the images (roofs within 1 m instead of on "
    "the ground; per-pixel change AUC: plain eq. 27 up, the default 3×3 down — docs/volume.md).",
)
@click.option("--supersample", type=int, default=1, show_default=True, help="k×k rays per pixel.")
@click.option(
    "--normalize",
    type=click.Choice(["equalize", "percentile", "scale"]),
    default="equalize",
    show_default=True,
    help="Per-image radiometric normalisation.",
)
@click.option(
    "--sun",
    nargs=2,
    type=float,
    default=None,
    help="Sun azimuth and elevation (degrees) of all images, when their metadata lacks it.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the image order.")
@click.pass_context
def update(
    ctx,
    model_dir,
    manifest_path,
    epochs,
    images,
    exclude,
    passes,
    finest_cell_m,
    max_depth,
    init_depth,
    above_m,
    fixed_grid,
    no_dem_prior,
    use_footprints,
    supersample,
    normalize,
    sun,
    seed,
):
    """Create or update the model in MODEL_DIR from images (saved after each pass, atomically)."""
    import numpy as np

    from ..errors import ConfigError
    from ..io.manifest import load_manifest
    from ..volume import VolumeModel, VolumeParams, load_model, save_model, update_model
    from ..volume.update import RAY_CACHE_MAX_RAYS
    from ..volume.io import geometry_from_manifest, read_view

    from ..io.outputs import open_outputs

    if passes < 1:
        raise ConfigError("--passes must be at least 1")
    man = load_manifest(manifest_path) if manifest_path else None
    open_outputs(None, files=[model_dir], inputs=[*(man.input_paths() if man else []), *images])
    specs = []
    if images:
        specs = [(Path(p), None, Path(p).stem) for p in images]
    elif man is not None:
        eps = [man.epoch(e) for e in epochs] if epochs else [man.epochs[0]]
        specs = [(im.path, im.camera, im.name) for e in eps for im in e.images]
    specs = [s for s in specs if s[2] not in set(exclude)]
    if not specs:
        raise ConfigError("no image to learn from: give --manifest (and --epoch) or --image")
    dem_seed = None
    if (Path(model_dir) / "model.json").is_file():
        model = load_model(model_dir)
        if man is not None and man.aoi is not None and man.aoi.crs:
            model.geometry.check_crs(man.aoi.crs, f"the manifest {man.path}")
        _say(ctx, f"updating {model_dir}: {model.n_leaves:,} leaves, {len(model.history)} updates so far")
    else:
        if man is None:
            raise ConfigError(f"{model_dir} holds no model; give --manifest to define its AOI and height range")
        geom, grid = geometry_from_manifest(man, finest_cell_m=finest_cell_m, max_depth=max_depth, above_m=above_m)
        params = VolumeParams(refine=not fixed_grid)
        model = VolumeModel.create(geom, params, init_depth=max_depth if fixed_grid else init_depth)
        _say(ctx, f"new model: {geom.n_blocks} blocks of {geom.block_size_m} m, finest cell {geom.finest_cell_m} m")
        if man.dem is not None and not no_dem_prior:
            from ..io.raster import read_dem

            dem = read_dem(man.dem.path, grid=grid, vertical_datum=man.dem.vertical_datum).to_ellipsoidal()
            dem_seed = (dem.height_m, grid)
    from .common import session

    # beside the model folder, not in it: every save replaces the folder as a whole
    session(ctx).open_log(Path(model_dir).resolve().parent)
    s = tuple(sun) if sun else None
    views = [read_view(p, c, name=n, sun=s, normalize=normalize) for p, c, n in specs]
    if dem_seed is not None:
        from ..volume.prior import roof_surface, seed_from_dem

        dem_m, grid = dem_seed
        roof = None
        if man.footprints is not None and use_footprints:
            from ..io.vector import polygons_to_mask, read_footprints

            fp = polygons_to_mask(
                read_footprints(man.footprints.path, crs=grid.crs, layer=man.footprints.layer), grid
            ).astype(bool)
            if fp.any():
                roof, ri = roof_surface(views, fp, dem_m, grid, step_m=model.geometry.finest_cell_m)
                _say(ctx, f"roof heights from the footprints: {ri['roofs']} of {ri['footprints']} footprints")
        info = seed_from_dem(model, dem_m, grid, roof_m=roof)
        _say(ctx, f"DEM prior: {info['ground_cells']:,} ground/roof cells, {info['air_cells']:,} air cells")
    rng = np.random.default_rng(seed)
    prog = _progress(ctx, "volume update")
    n_total = passes * len(views)
    k = 0
    # each view's rays kept from pass to pass when the views are small enough (else recomputed per pass)
    small = sum(v.intensity.size for v in views) * supersample**2 <= RAY_CACHE_MAX_RAYS
    rays = [{} if small else None for _ in views]
    try:
        for p in range(passes):
            for i in rng.permutation(len(views)):
                v = views[i]
                base = k / n_total

                def sub(f, msg="", _b=base):
                    prog(_b + (f or 0.0) / n_total, f"pass {p + 1}/{passes} {v.name}: {msg}")

                update_model(
                    model,
                    v.intensity,
                    v.camera,
                    sun=v.sun,
                    name=v.name,
                    supersample=supersample,
                    ray_cache=rays[i],
                    progress=sub,
                )
                k += 1
            save_model(model, model_dir)
    finally:
        _close(prog)
    rep = model.size_report()
    session(ctx).say(
        f"{rep['leaves']:,} leaves ({rep['bytes'] / 2**20:.1f} MiB); a fixed grid at {rep['finest_cell_m']} m "
        f"would take {rep['fixed_grid_ratio']:.1f}x more"
    )
    from . import emit_result

    emit_result(ctx, {"model": model_dir})


@volume.command("detect")
@click.argument("model_dir", type=click.Path(exists=True, file_okay=False, path_type=str))
@click.argument("image", type=click.Path(exists=True, dir_okay=False, path_type=str))
@click.option(
    "--camera",
    "camera_path",
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    default=None,
    help="Camera file of the image (default: found next to it).",
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(path_type=str),
    default=None,
    help="Output folder (default: ./geocd_out/volume_detect).",
)
@click.option(
    "--neighborhood",
    type=int,
    default=3,
    show_default=True,
    help="n of the n×n variant (odd): a pixel's value is scored against the rays of its n×n neighbours, "
    "which absorbs the ±1 px registration of 0.5 m cells at 0.5 m pixels (1 = the plain eq. 27).",
)
@click.option("--prior", type=float, default=0.5, show_default=True, help="Prior probability of change.")
@click.option("--no-relight", is_flag=True, help="Use the nearest sun bin's appearance as is (paper's behaviour).")
@click.option(
    "--posting",
    "posting_m",
    type=float,
    default=None,
    help="Posting of the orthorectified outputs, metres (default: the finest cell).",
)
@click.option(
    "--normalize", type=click.Choice(["equalize", "percentile", "scale"]), default="equalize", show_default=True
)
@click.option("--sun", nargs=2, type=float, default=None, help="Sun azimuth and elevation of the image (degrees).")
@click.option(
    "--shadow-dsm",
    "shadow_dsm",
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    default=None,
    help="A DSM of the model's training epoch (e.g. geocd ortho's dsm_A.tif; any CRS and datum GDAL "
    "reads): when the image is relit, shadows under both suns are cast from it instead of the "
    "model's own density, whose building interiors are empty.",
)
@click.pass_context
def detect(
    ctx, model_dir, image, camera_path, out_dir, neighborhood, prior, no_relight, posting_m, normalize, sun, shadow_dsm
):
    """Change probability of IMAGE against the model: image geometry and orthorectified GeoTIFFs."""
    import json

    import numpy as np

    from ..io.atomic import write_text_atomic
    from ..io.outputs import open_outputs
    from ..io.raster import write_cog
    from ..volume import DetectParams, detect_change, expected_height_map, load_model, orthorectify
    from ..volume.io import read_shadow_dsm, read_view

    from .common import resolve_out_dir, session

    out = out_dir = resolve_out_dir(out_dir, "volume_detect", create=False)
    model = load_model(model_dir)  # checked (a damaged model is refused) before the output folder is touched
    open_outputs(
        out_dir, inputs=[model_dir, image, camera_path, shadow_dsm], products=("*_change_prob*", "*_change.json")
    )
    session(ctx).open_log(out)
    v = read_view(image, camera_path, sun=tuple(sun) if sun else None, normalize=normalize)
    shadow = None
    if shadow_dsm:
        shadow = read_shadow_dsm(shadow_dsm, model.geometry.aoi_grid(model.geometry.finest_cell_m))
    prog = _progress(ctx, "volume detect")
    try:
        res = detect_change(
            model,
            v.intensity,
            v.camera,
            sun=v.sun,
            name=v.name,
            params=DetectParams(prior=prior, neighborhood=neighborhood, relight=not no_relight),
            shadow_dsm=shadow,
            progress=lambda f, m="": prog(0.8 * (f or 0.0), m),
        )
        h, grid = expected_height_map(
            model, posting_m=posting_m, progress=lambda f, m="": prog(0.8 + 0.1 * (f or 0), m)
        )
        ortho = orthorectify(res.probability, v.camera, h, grid)
        prog(0.95, "writing")
    finally:
        _close(prog)
    outputs = {}
    p_img = out / f"{v.name}_change_prob.tif"
    _write_image_geometry(
        p_img,
        np.stack([res.probability, res.expected, res.vis_inf]),
        image,
        ["change_probability", "expected_intensity", "vis_inf"],
    )
    outputs["change_probability"] = p_img
    p_ortho = out / f"{v.name}_change_prob_ortho.tif"
    write_cog(
        p_ortho,
        {"change_probability": ortho},
        grid,
        tags={"method": "geocd.volume (Crispell et al. eq. 27)", "image": v.name, "model": str(model_dir)},
    )
    outputs["change_probability_ortho"] = p_ortho
    meta = {
        "image": str(image),
        "sun": v.sun,
        "sun_bin": res.sun_bin,
        "sun_offset_deg": res.sun_offset_deg,
        "unknown_fraction": float(res.unknown.mean()),
        "relight": res.relight,
        "mean_change_probability": float(np.nanmean(res.probability)) if np.isfinite(res.probability).any() else None,
    }
    p_meta = out / f"{v.name}_change.json"
    write_text_atomic(p_meta, json.dumps(meta, indent=1))
    outputs["summary"] = p_meta
    mcp = meta["mean_change_probability"]
    session(ctx).say(
        f"{v.name}: mean change probability {mcp:.3f}"
        if mcp is not None
        else f"{v.name}: no pixel of the image sees the model"
    )
    if res.relight is not None and shadow is None:
        session(ctx).say(
            f"{v.name} was relit to a sun {res.sun_offset_deg:.0f}° from the model's; its shadows were "
            "predicted from the model's own density. --shadow-dsm with a DSM of the training epoch "
            "(e.g. geocd ortho's dsm_A.tif) casts them from the surface instead (docs/volume.md)."
        )
    from . import emit_result

    emit_result(ctx, outputs)


def _write_image_geometry(path: Path, bands, source_image: str, names) -> None:
    """A float32 raster in the source image's geometry, carrying its RPC tags when it has some."""
    import rasterio

    from ..io.atomic import atomic_path

    import warnings

    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        src = rasterio.open(source_image)
    with src:
        rpcs = src.rpcs
        gcps = src.gcps
    profile = {
        "driver": "GTiff",
        "width": bands.shape[2],
        "height": bands.shape[1],
        "count": bands.shape[0],
        "dtype": "float32",
        "nodata": float("nan"),
        "compress": "deflate",
        "tiled": True,
    }
    with atomic_path(path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(bands.astype("float32"))
            for i, n in enumerate(names, start=1):
                dst.set_band_description(i, n)
            if rpcs is not None:
                dst.rpcs = rpcs
            elif gcps and gcps[0]:
                dst.gcps = gcps


@volume.command("render")
@click.argument("model_dir", type=click.Path(exists=True, file_okay=False, path_type=str))
@click.option(
    "--image",
    "images",
    multiple=True,
    type=click.Path(exists=True, dir_okay=False, path_type=str),
    help="Render the expected image of this image's view (repeatable).",
)
@click.option("--height-map", is_flag=True, help="Write the expected height map (ellipsoidal DEM, COG).")
@click.option("--posting", "posting_m", type=float, default=None, help="Height-map posting, metres.")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(path_type=str),
    default=None,
    help="Output folder (default: ./geocd_out/volume_render).",
)
@click.pass_context
def render(ctx, model_dir, images, height_map, posting_m, out_dir):
    """Expected images of views and/or the expected height map of the model."""
    import numpy as np

    from ..errors import ConfigError
    from ..io.raster import write_cog
    from ..volume import expected_height_map, expected_image, load_model
    from ..volume.io import read_view

    from ..io.outputs import open_outputs
    from .common import resolve_out_dir, session

    if not images and not height_map:
        raise ConfigError("nothing to render: give --image and/or --height-map")
    out = out_dir = resolve_out_dir(out_dir, "volume_render", create=False)
    model = load_model(model_dir)  # checked (a damaged model is refused) before the output folder is touched
    open_outputs(out_dir, inputs=[model_dir, *images], products=("*_expected.tif", "expected_height_map.tif"))
    session(ctx).open_log(out)
    outputs = {}
    prog = _progress(ctx, "volume render")
    try:
        n = len(images) + int(height_map)
        for i, im in enumerate(images):
            v = read_view(im)
            r = expected_image(
                model,
                v.camera,
                v.intensity.shape,
                sun=v.sun,
                progress=lambda f, m="", _i=i: prog((_i + (f or 0)) / n, m),
            )
            p = out / f"{v.name}_expected.tif"
            _write_image_geometry(p, np.stack([r.expected, r.vis_inf]), im, ["expected_intensity", "vis_inf"])
            outputs[f"expected:{v.name}"] = p
        if height_map:
            h, grid = expected_height_map(
                model, posting_m=posting_m, progress=lambda f, m="": prog((len(images) + (f or 0)) / n, m)
            )
            p = out / "expected_height_map.tif"
            write_cog(
                p,
                {"height_m": h},
                grid,
                tags={
                    "vertical_datum": "ellipsoid (WGS84)",
                    "method": "geocd.volume median visible surface from above",
                },
            )
            outputs["height_map"] = p
    finally:
        _close(prog)
    from . import emit_result

    emit_result(ctx, outputs)
