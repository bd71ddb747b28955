"""``geocd mpp``: buildings and their changes between two dates (marked point process of rectangles)."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from .common import pixel_size_option


def check_change_prior(path: str | Path) -> None:
    """Check a ``--change-prior`` raster up front (before any stereo or ortho): a georeferenced raster whose
    ``confidence`` band (or first band) holds 0–1 or 0–100 values, read on a decimated sample.

    Raises
    ------
    UnsupportedFormatError, CRSError, ConfigError, EmptyDataError
    """
    from ..errors import ConfigError, CRSError, EmptyDataError
    from ..io.raster import _open, _read_failure

    with _open(path) as ds:
        if ds.crs is None:
            raise CRSError(
                f"--change-prior {path} has no CRS: it must be a georeferenced map (e.g. OUT/sc_change.tif "
                "from geocd run) to be laid on the grid"
            )
        names = list(ds.descriptions)
        band = names.index("confidence") + 1 if "confidence" in names else 1
        if not np.issubdtype(np.dtype(ds.dtypes[band - 1]), np.number) or np.dtype(ds.dtypes[band - 1]).kind == "c":
            raise ConfigError(f"--change-prior {path} band {band} is {ds.dtypes[band - 1]}, not a real number")
        step = max(1, int(np.ceil(max(ds.width, ds.height) / 512)))
        try:
            a = ds.read(band, out_shape=(max(1, ds.height // step), max(1, ds.width // step)), masked=True)
        except Exception as exc:  # noqa: BLE001 - GDAL's read failures have many types
            raise _read_failure(path, exc) from None
    v = np.asarray(a.astype(np.float64).filled(np.nan))
    v = v[np.isfinite(v)]
    if v.size == 0:
        raise EmptyDataError(f"--change-prior {path} holds no valid value; give a 0–1 or 0–100 change map")
    lo, hi = float(v.min()), float(v.max())
    if lo < 0.0 or hi > 100.0:
        raise ConfigError(
            f"--change-prior {path} holds values {lo:g}..{hi:g}; it must be a 0–1 or 0–100 (%) change "
            "map, e.g. OUT/sc_change.tif (band 'confidence') from geocd run"
        )


@click.command("mpp")
@click.argument("manifest", required=False, type=click.Path(path_type=str))
@click.option(
    "--image-a",
    type=click.Path(path_type=str),
    default=None,
    help="The earlier image. With a manifest: an image name of epoch A (default: the most vertical view); "
    "without: a georeferenced image file (e.g. a geocd ortho).",
)
@click.option(
    "--image-b",
    type=click.Path(path_type=str),
    default=None,
    help="The later image. With a manifest: an image name of epoch B (default: the most vertical view); "
    "without: a georeferenced image file (resampled onto the earlier one's grid if needed).",
)
@click.option(
    "--dsm-a",
    type=click.Path(path_type=str),
    default=None,
    help="Surface model of the earlier date (height term). Manifest default: geocd stereo's.",
)
@click.option("--dsm-b", type=click.Path(path_type=str), default=None, help="Surface model of the later date.")
@click.option(
    "--ground",
    "ground",
    type=click.Path(path_type=str),
    default=None,
    help="With --image-a/--image-b: terrain DEM (default: estimated from each DSM).",
)
@click.option("--epoch-a", default=None, help="Manifest: earlier epoch (default the first).")
@click.option("--epoch-b", default=None, help="Manifest: later epoch (default the last).")
@click.option(
    "--method",
    type=click.Choice(["ED", "SD", "EV"]),
    default="ED",
    show_default=True,
    help="ED joint model (the paper's), SD each date alone then compared, EV edge-only verification.",
)
@click.option(
    "--height",
    type=click.Choice(["auto", "on", "off"]),
    default="auto",
    show_default=True,
    help="Height term from the DSMs (auto: when DSMs are available).",
)
@click.option(
    "--step",
    type=click.Choice(["and", "ring", "off"]),
    default="off",
    show_default=True,
    help="Height-step term (with the height term): 'and' a building's outline must step down "
    "steeply along most of its length; 'ring' the step may stand in for ground around it (dense "
    "blocks); 'off' none.",
)
@click.option(
    "--edge-fit",
    "edge_fit",
    type=click.Choice(["joint", "image", "off"]),
    default="joint",
    show_default=True,
    help="After the annealing, move each side of each building rectangle (¼-cell steps, within the "
    "ring width) onto the image's strongest edge across it: 'joint' only where the DSM has a wall "
    "there, 'image' the image edge alone, 'off' none.",
)
@click.option(
    "--edge-fit-turn",
    "edge_fit_turn",
    type=click.Choice(["on", "off"]),
    default="on",
    show_default=True,
    help="With the edge fit: after the sides, turn each rectangle about its centre (within 15°, 3 σ of "
    "the births' angle noise) to the angle of its strongest image edges, kept when those edges do not "
    "weaken and its energy does not rise; 'off' the sides only.",
)
@click.option(
    "--edge-fit-grow",
    "edge_fit_grow",
    type=click.Choice(["on", "off"]),
    default="on",
    show_default=True,
    help="With the joint edge fit and DSMs: push each rectangle's sides out over the raised block it "
    "stands on (while most of the strip beyond a side stands above half its height on every date "
    "it exists on, not into another rectangle nor across the valley between two buildings), then "
    "onto the walls; kept when the object stays attractive. 'off': no growth.",
)
@click.option(
    "--edge-fit-carve",
    "edge_fit_carve",
    type=click.Choice(["on", "off"]),
    default="on",
    show_default=True,
    help="With the joint edge fit and DSMs: cut a corner notch from a rectangle, making an L of two "
    "rectangles, when the notch is not raised and its two inner sides are image edges on every "
    "date the building exists on. 'off': rectangles only.",
)
@click.option(
    "--wall-blur",
    "wall_blur",
    type=click.Choice(["off", "measured"]),
    default="off",
    show_default=True,
    help="How the height term reads the DSM's blurred walls: 'measured' the blur is measured on each "
    "image (the DSM's profile across the image's edges) and the height ring and the raised fraction "
    "read it; 'off' the plain term.",
)
@click.option(
    "--absence",
    type=click.Choice(["height", "off"]),
    default="off",
    show_default=True,
    help="With the height term: 'height' a new or demolished label needs ground under the object in the "
    "other date's DSM (over half of its cells at most min-height above the ground; a tree crown "
    "standing there contradicts it); 'off' the paper's change terms only.",
)
@click.option(
    "--change-evidence",
    "change_evidence",
    type=click.Choice(["height", "texture", "both"]),
    default="height",
    show_default=True,
    help="With the height term: what says a building changed. 'height' the DSMs (a cell stands above "
    "min-height on one date only); 'texture' the paper's gradient-orientation similarity of the "
    "two images; 'both' their mean. Without DSMs the texture.",
)
@click.option(
    "--change-prior",
    type=click.Path(path_type=str),
    default=None,
    help="3-D change evidence as a prior on the change label: a geocd change raster (band 'confidence', "
    "e.g. OUT/sc_change.tif from geocd run) or any 0–1 map.",
)
@click.option("--gamma-3d", type=float, default=None, help="Weight of the 3-D change prior (default 1 when given).")
@click.option("--side-min", "side_min_m", type=float, default=None, help="Smallest rectangle side, m (default 6).")
@click.option(
    "--side-max",
    "side_max_m",
    type=float,
    default=None,
    help="Largest rectangle side, m (default: 30, raised to the 0.9 quantile of the raised segments' "
    "long sides when DSMs are used).",
)
@click.option(
    "--prototypes",
    default=None,
    help="Object prototypes: 'auto' (default: chosen from the data) or features joined by '+' (AND) and "
    "'|' (OR) from gradient, homogeneity, colour, shadow, height, planarity; with the height term "
    "every prototype also needs height (and planarity), e.g. 'gradient|homogeneity|planarity' lets "
    "a raised planar block of the DSM stand without an image cue.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed: same seed, same objects.")
@click.option("--max-iter", type=int, default=None, help="Iteration cap of multiple birth and death (default 250).")
@click.option("--posting", "posting_m", type=float, default=None, help="Grid posting in metres.")
@pixel_size_option("--image-a/--image-b")
@click.option(
    "--surface-median",
    "surface_median",
    type=int,
    default=None,
    help="Manifest: the surface median (odd cells) of the stereo that makes the DSMs. Default 1 (off: "
    "each cell's own match, as geocd run): the height cues measure the DSM's noise on the DSM "
    "itself. docs/mpp.md measures both.",
)
@click.option(
    "--out",
    "out",
    type=click.Path(path_type=str),
    default=None,
    help="Output folder (manifest default: its output; layers go to OUT/mpp/).",
)
@click.option("--no-overwrite", is_flag=True, help="Fail instead of replacing existing outputs.")
@click.pass_context
def mpp(
    ctx: click.Context,
    manifest,
    image_a,
    image_b,
    dsm_a,
    dsm_b,
    ground,
    epoch_a,
    epoch_b,
    method,
    height,
    step,
    edge_fit,
    edge_fit_turn,
    edge_fit_grow,
    edge_fit_carve,
    wall_blur,
    absence,
    change_evidence,
    change_prior,
    gamma_3d,
    side_min_m,
    side_max_m,
    prototypes,
    seed,
    max_iter,
    posting_m,
    pixel_size,
    surface_median,
    out,
    no_overwrite,
) -> None:
    """Find buildings on two images of different dates and which are new, demolished or unchanged: a marked
    point process of rectangles optimised by multiple birth and death (Benedek, Descombes & Zerubia), with
    geocd's height term from the DSMs.

    Give a MANIFEST (one view per epoch, --image-a/--image-b by name, is orthorectified on geocd stereo's DSM) or
    two image files with --image-a/--image-b.
    Writes mpp_buildings.gpkg (layers buildings and rectangles, styled, confidence in %), mpp_buildings.tif,
    a quick-look PNG and mpp_summary.json.
    """
    from ..errors import ConfigError
    from ..mpp.params import MPPParams
    from . import emit_result, make_progress
    from ..io.plain import on_local_grid
    from .common import require_inputs, resolve_out_dir, session

    sess = session(ctx)
    view_a = view_b = None
    if manifest is not None:  # the images are names of the manifest's views
        view_a, view_b, image_a, image_b = image_a, image_b, None, None
    elif (image_a is None) != (image_b is None):
        raise ConfigError("give both --image-a and --image-b, or a manifest")
    if manifest is None and image_a is None:
        raise ConfigError("give a scene manifest, or two images with --image-a and --image-b")
    if surface_median is not None and manifest is None:
        raise ConfigError(
            "--surface-median applies to the stereo DSMs of a manifest; with --image-a/--image-b give --dsm-a/--dsm-b"
        )
    if pixel_size is not None and manifest is not None:
        raise ConfigError("--pixel-size is for two plain images (--image-a/--image-b); a manifest's views have cameras")
    if height == "on" and image_a is not None and dsm_a is None:
        raise ConfigError("--height on needs --dsm-a and --dsm-b with --image-a/--image-b")
    require_inputs(manifest, image_a, image_b, dsm_a, dsm_b, ground, change_prior)
    if ground is not None and manifest is not None:
        raise ConfigError(
            "--ground is the terrain for --image-a/--image-b; with a manifest the ground is the "
            "manifest's dem: (or estimated from each DSM): leave --ground out or put it in the manifest"
        )
    from ..io.raster import check_dem_file

    for dem in (dsm_a, dsm_b, ground):  # every DEM check before any ortho or stereo is written
        if dem is not None:
            check_dem_file(dem)
    if change_prior is not None:
        check_change_prior(change_prior)
    kw = {"seed": seed}
    for k, v in (
        ("side_min_m", side_min_m),
        ("side_max_m", side_max_m),
        ("max_iter", max_iter),
        ("gamma_3d", gamma_3d),
        ("prototypes", prototypes),
        ("step", step),
        ("edge_fit", edge_fit),
        ("wall_blur", wall_blur),
        ("absence", absence),
        ("change_evidence", change_evidence),
    ):
        if v is not None:
            kw[k] = v
    if side_max_m is not None:
        kw["side_max_from_dsm"] = False
    kw["edge_fit_rotate"] = edge_fit_turn == "on"
    kw["edge_fit_grow"] = edge_fit_grow == "on"
    kw["edge_fit_carve"] = edge_fit_carve == "on"
    params = MPPParams(**kw)
    from ..io.outputs import open_outputs

    progress = make_progress(ctx, "mpp")
    try:
        if manifest is not None:
            from ..io.manifest import load_manifest
            from ..mpp.pipeline import run_mpp_manifest
            from ..io.manifest import pick_epochs

            m = load_manifest(manifest)
            out_dir = Path(out) if out else m.output_dir()
            open_outputs(
                out_dir,
                inputs=[*m.input_paths(), dsm_a, dsm_b, change_prior],
                products=("mpp/*", "ortho/*", "stereo/*"),
            )
            sess.open_log(out_dir)
            dsm = None
            if dsm_a or dsm_b:
                ea, eb = pick_epochs(m, epoch_a, epoch_b)
                dsm = {k: v for k, v in ((ea.name, dsm_a), (eb.name, dsm_b)) if v}
            sp = None
            if surface_median is not None:
                from ..stereo.params import StereoParams

                sp = StereoParams(surface_median=surface_median)
            res = run_mpp_manifest(
                m,
                out_dir=out_dir,
                epoch_a=epoch_a,
                epoch_b=epoch_b,
                view_a=view_a,
                view_b=view_b,
                dsm=dsm,
                method=method,
                params=params,
                height=height,
                change_prior=change_prior,
                posting_m=posting_m,
                overwrite=not no_overwrite,
                stereo_params=sp,
                progress=progress,
            )
        else:
            from ..mpp.pipeline import run_mpp_images

            with on_local_grid([[image_a, image_b]], pixel_size) as ((grid_a, grid_b),):
                out_dir = resolve_out_dir(out, Path(image_a).stem + "_mpp")
                open_outputs(
                    out_dir, inputs=[image_a, image_b, dsm_a, dsm_b, ground, change_prior], products=("mpp_*",)
                )
                sess.open_log(out_dir)
                if pixel_size is not None:
                    sess.note(f"plain images on a local grid of {pixel_size:g} m pixels (no map CRS)")
                res = run_mpp_images(
                    grid_a,
                    grid_b,
                    out_dir=out_dir,
                    dsm_a=dsm_a if height != "off" else None,
                    dsm_b=dsm_b if height != "off" else None,
                    ground=ground,
                    method=method,
                    params=params,
                    change_prior=change_prior,
                    posting_m=posting_m,
                    overwrite=not no_overwrite,
                    progress=progress,
                )
    finally:
        if hasattr(progress, "close"):
            progress.close()
    det = res["detection"]
    for n in det.notes:
        sess.note(n)
    r = det.result
    counts = {XI: int(np.count_nonzero(r.xi == k)) for k, XI in ((0, "unchanged"), (1, "demolished"), (2, "new"))}
    sess.say(
        f"{len(r)} rectangles: {counts['unchanged']} unchanged, {counts['demolished']} demolished, "
        f"{counts['new']} new ({r.iterations} iterations, {'converged' if r.converged else 'not converged'})"
    )
    sess.data(
        rectangles=len(r),
        by_change=counts,
        iterations=r.iterations,
        converged=r.converged,
        method=det.method,
        height=res["params"].height,
    )
    emit_result(ctx, {k: v for k, v in res["outputs"].items() if not k.startswith("ortho:")})
