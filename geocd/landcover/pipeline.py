"""Land-cover files: read images, labels, DEMs and footprints; train, predict, project, integrate; write products.

The only part of :mod:`geocd.landcover` that touches files. Everything it
computes goes through the array functions of :mod:`.features`,
:mod:`.classifier`, :mod:`.project` and :mod:`.gp`, so a tiling layer can run
the same steps per AOI window.
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..camera import Camera
from ..errors import ConfigError, GridError, NoCameraError
from ..geodesy import AOIGrid, as_crs
from ..progress import ensure_progress, sub_progress
from .classifier import LabelError, LandcoverModel, load_model, predict_proba, save_model, train
from .features import FeatureSpec, pixel_features
from .labels import class_list, pixel_layer_rows, polygons_for_image, rasterize_labels, read_labels
from .project import ProjectedView, building_surface, cell_pixels, combine_views, grid_to_image, project_view


# ---------------------------------------------------------------------------------------------
# scene context: grid, surface, occupancy
# ---------------------------------------------------------------------------------------------
@dataclass
class Scene:
    """Where the ground grid is and what the rays meet.

    Attributes
    ----------
    grid : AOIGrid
    dem_m : float64 (rows, cols), ellipsoidal terrain heights (NaN = none)
    surface_m : float64 (rows, cols), DSM (given) or DEM + extruded footprints
    occupancy : float32 (rows, cols), building fraction of each cell (0 without footprints)
    has_dsm : bool, a real DSM (not only footprints) gives the surface
    """

    grid: AOIGrid
    dem_m: np.ndarray
    surface_m: np.ndarray
    occupancy: np.ndarray
    has_dsm: bool = False

    @property
    def height_above_ground_m(self) -> np.ndarray:
        return (self.surface_m - self.dem_m).astype(np.float32)


def load_scene(
    *,
    manifest=None,
    dem: str | None = None,
    dem_datum: str | None = None,
    footprints: str | None = None,
    dsm: str | None = None,
    height_field: str | None = None,
    bounds: Sequence[float] | None = None,
    posting_m: float | None = None,
    crs: Any = None,
) -> Scene:
    """Build the :class:`Scene` from a manifest and/or explicit files (explicit files win)."""
    from ..io.manifest import Manifest, load_manifest
    from ..io.raster import _open, read_dem
    from ..io.vector import read_footprints

    m = None
    footprints_layer = None
    if manifest is not None:
        m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
        if dem is None and m.dem is not None:
            dem, dem_datum = str(m.dem.path), dem_datum or m.dem.vertical_datum
        if footprints is None and m.footprints is not None:
            fp_spec = m.footprints  # a path, or a spec with .path and .layer
            footprints = str(getattr(fp_spec, "path", fp_spec))
            footprints_layer = getattr(fp_spec, "layer", None)
        if m.aoi is not None:
            crs = crs or m.aoi.crs
            bounds = bounds or m.aoi.bounds
            posting_m = posting_m or m.aoi.posting_m
    if dem is None:
        raise ConfigError("land-cover projection needs terrain heights: give --dem (or a manifest with a DEM)")
    if bounds is None or crs is None or posting_m is None:
        with _open(dem) as ds:
            g0 = AOIGrid.from_raster(ds)
        crs = crs or g0.crs
        if bounds is None:
            if not as_crs(crs).equals(g0.crs):
                raise ConfigError("give --bounds in the grid CRS when it differs from the DEM's CRS")
            bounds = g0.bounds
        posting_m = posting_m or g0.posting_m
    grid = AOIGrid.from_bounds(*bounds, posting_m, as_crs(crs))
    d = read_dem(dem, grid=grid, vertical_datum=dem_datum).to_ellipsoidal().height_m.astype(np.float64)
    fp = read_footprints(footprints, crs=grid.crs, layer=footprints_layer) if footprints else None
    surface, occ = building_surface(d, grid, fp, height_field)
    has_dsm = False
    if dsm is not None:
        s = read_dem(dsm, grid=grid).to_ellipsoidal().height_m.astype(np.float64)
        surface = np.where(np.isfinite(s), s, surface)
        has_dsm = True
    return Scene(grid=grid, dem_m=d, surface_m=surface, occupancy=occ, has_dsm=has_dsm)


# ---------------------------------------------------------------------------------------------
# images
# ---------------------------------------------------------------------------------------------
@dataclass
class LoadedImage:
    """An image with either a camera (raw RPC/frame image) or a map georeference (orthoimage)."""

    path: Path
    data: np.ndarray
    valid: np.ndarray
    camera: Camera | None
    crs: Any
    transform: Any

    @property
    def name(self) -> str:
        return self.path.stem

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape[1:]

    @property
    def is_ortho(self) -> bool:
        return self.camera is None and self.crs is not None


def load_image(path: os.PathLike | str, camera: os.PathLike | str | None = None) -> LoadedImage:
    """Read an image and its camera (RPC tags/sidecar or frame sidecar), else its map georeference."""
    from ..io.cameras import load_camera
    from ..io.raster import read_image

    img = read_image(path)
    cam = None
    try:
        cam = load_camera(path, camera)
    except NoCameraError:
        if img.crs is None:
            cam = None
    return LoadedImage(Path(path), img.data, img.valid, cam, img.crs, img.transform)


def image_gsd_m(camera: Camera, shape: tuple[int, int], h: float) -> float:
    """Ground distance (m) between the centres of two neighbouring pixels at the image centre, height ``h``."""
    from ..geodesy import LocalFrame

    r, c = shape[0] / 2.0, shape[1] / 2.0
    lon, lat = camera.localize(np.array([c, c + 1.0, c]), np.array([r, r, r + 1.0]), np.full(3, h))
    if not np.all(np.isfinite(lon)):
        return float("nan")
    fr = LocalFrame(float(lon[0]), float(lat[0]), h)
    e, n, _ = fr.to_enu(lon, lat, np.full(3, h))
    return float(math.sqrt(math.hypot(e[1] - e[0], n[1] - n[0]) * math.hypot(e[2] - e[0], n[2] - n[0])))


def _image_hag(im: LoadedImage, scene: Scene | None, geometry=None) -> np.ndarray | None:
    """Height above ground of what each pixel sees (from the scene's surface), NaN where unknown."""
    if scene is None:
        return None
    if im.is_ortho:
        from ..io.raster import reproject_array

        g = AOIGrid(as_crs(im.crs), im.transform, im.shape[1], im.shape[0])
        return reproject_array(scene.height_above_ground_m, scene.grid, g, "nearest")
    rows, cols, obs = cell_pixels(im.camera, scene.grid, scene.surface_m, im.shape, geometry)
    return grid_to_image(
        scene.height_above_ground_m, rows, cols, obs, im.shape, max_gap_px=3.0 * max(1.0, _px_per_cell(im, scene))
    )


def _px_per_cell(im: LoadedImage, scene: Scene) -> float:
    h = float(np.nanmedian(scene.dem_m))
    g = image_gsd_m(im.camera, im.shape, h) if im.camera is not None else abs(im.transform.a)
    return float(scene.grid.posting_m / g) if g and np.isfinite(g) else 1.0


def image_features(im: LoadedImage, spec: FeatureSpec, scene: Scene | None = None) -> np.ndarray:
    """Feature stack of a loaded image (height above ground from the scene when the spec asks for it)."""
    hag = None
    if spec.height_above_ground:
        if scene is None or not scene.has_dsm and not scene.occupancy.any():
            raise ConfigError(
                "the feature set uses the height above ground: give a DSM (--dsm) or footprints with heights, and a DEM"
            )
        hag = _image_hag(im, scene)
    return pixel_features(im.data, im.valid, spec, hag)


# ---------------------------------------------------------------------------------------------
# training
# ---------------------------------------------------------------------------------------------
def label_pixels(labels, im: LoadedImage, classes: list[str], scene: Scene | None) -> tuple[np.ndarray, np.ndarray]:
    """Class index and polygon id (−1 = none) of every pixel of ``im``.

    Layers without a CRS are pixel coordinates of the image; georeferenced layers reach an
    orthoimage through its geotransform, and a raw image through the scene grid and its camera
    (only cells the camera sees: a label behind a building is not given to the roof).
    """
    from affine import Affine

    if labels.crs is None:
        sub = pixel_layer_rows(polygons_for_image(labels, im.path), im.shape)
        return rasterize_labels(sub, im.shape, Affine.identity(), classes)
    if im.is_ortho:
        sub = labels.to_crs(as_crs(im.crs))
        return rasterize_labels(sub, im.shape, im.transform, classes)
    if scene is None:
        raise ConfigError(
            f"labels drawn on the map reach {im.name} through its camera: give the terrain (--dem or a "
            "manifest) so geocd knows where the ground is"
        )
    sub = labels.to_crs(scene.grid.crs)
    g_cls, g_pid = rasterize_labels(sub, scene.grid.shape, scene.grid.transform, classes)
    cls = np.full(im.shape, -1, np.int16)
    pid = np.full(im.shape, -1, np.int32)
    if not (g_cls >= 0).any():
        return cls, pid
    rows, cols, obs = cell_pixels(im.camera, scene.grid, scene.surface_m, im.shape)
    ok = obs & (g_cls >= 0)
    cls[rows[ok], cols[ok]] = g_cls[ok]
    pid[rows[ok], cols[ok]] = g_pid[ok]
    # a labelled cell covers (posting / gsd)² pixels: grow each painted pixel over its cell's footprint
    r = int(max(0, round(_px_per_cell(im, scene) / 2.0 - 0.5)))
    if r > 0:
        from scipy import ndimage

        miss = cls < 0
        dist, (ii, jj) = ndimage.distance_transform_edt(miss, return_indices=True)
        grow = miss & (dist <= r)
        cls[grow] = cls[ii[grow], jj[grow]]
        pid[grow] = pid[ii[grow], jj[grow]]
    return cls, pid


def training_set(
    labels,
    images: Sequence[LoadedImage],
    classes: list[str],
    spec: FeatureSpec,
    scene: Scene | None = None,
    progress=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Samples (X, y, polygon id) from every image's labelled valid pixels, and a per-image count."""
    prog = ensure_progress(progress)
    Xs, ys, gs = [], [], []
    per_image: dict[str, int] = {}
    for k, im in enumerate(images):
        prog(k / max(1, len(images)), f"labels and features of {im.name}")
        cls, pid = label_pixels(labels, im, classes, scene)
        sel = (cls >= 0) & im.valid
        per_image[im.name] = int(sel.sum())
        if not sel.any():
            continue
        F = image_features(im, spec, scene)
        Xs.append(F[:, sel].T)
        ys.append(cls[sel].astype(np.int64))
        gs.append(pid[sel].astype(np.int64))
    if not Xs:
        raise LabelError(
            f"none of the {len(labels)} label polygons falls on a valid pixel of any image "
            f"({', '.join(im.name for im in images)}); draw them over the images (check the layer's "
            "CRS, or the image attribute of pixel-coordinate labels)"
        )
    return np.concatenate(Xs), np.concatenate(ys), np.concatenate(gs), per_image


def train_from_files(
    labels_path: os.PathLike | str,
    image_paths: Sequence[str],
    out_path: os.PathLike | str,
    *,
    cameras: Sequence[str | None] | None = None,
    layer: str | None = None,
    class_field: str | None = None,
    positive: str | None = None,
    method: str = "rf",
    spec: FeatureSpec = FeatureSpec(),
    scene: Scene | None = None,
    compare: bool = False,
    seed: int = 0,
    progress=None,
) -> dict:
    """Train a pixel classifier from label polygons over images; write the model (+ a JSON report)."""
    from ..io.atomic import protect_inputs, write_text_atomic

    prog = ensure_progress(progress)
    if not image_paths:
        raise ConfigError("give at least one image to train on (--image)")
    protect_inputs(labels_path, *image_paths)
    labels = read_labels(labels_path, layer, class_field)
    classes = class_list(labels, positive)
    if len(classes) < 2:
        raise LabelError(
            f"the labels hold a single class ({classes[0]!r}); draw polygons of at least two classes "
            "(e.g. the condition and 'other')"
        )
    cams = list(cameras) if cameras else [None] * len(image_paths)
    images = [load_image(p, c) for p, c in zip(image_paths, cams)]
    bands = {im.data.shape[0] for im in images}
    if len(bands) > 1:
        raise ConfigError(f"training images have different band counts {sorted(bands)}; train one model per sensor")
    X, y, g, per_image = training_set(labels, images, classes, spec, scene, sub_progress(prog, 0.0, 0.5))
    gsds = []
    if scene is not None:
        h = float(np.nanmedian(scene.dem_m))
        gsds = [image_gsd_m(im.camera, im.shape, h) for im in images if im.camera is not None]
    gsd = float(np.nanmedian(gsds)) if gsds else None
    prog(0.55, f"training ({method}) on {len(y)} labelled pixels")
    t0 = time.perf_counter()
    model = train(
        X, y, classes, spec, images[0].data.shape[0], method=method, seed=seed, groups=g, compare=compare, gsd_m=gsd
    )
    model.report["train_s"] = round(time.perf_counter() - t0, 2)
    model.report["labelled_pixels_per_image"] = per_image
    model.report["polygons"] = int(len(labels))
    out = save_model(model, out_path)
    rep_path = Path(out).with_suffix(".json")
    write_text_atomic(
        rep_path,
        json.dumps(
            {
                "classes": model.classes,
                "features": model.feature_names,
                "spec": spec.to_dict(),
                "gsd_m": gsd,
                **model.report,
            },
            indent=2,
        ),
    )
    prog(1.0, "model written")
    return {"outputs": {"model": out, "report": rep_path}, "model": model}


# ---------------------------------------------------------------------------------------------
# prediction and projection
# ---------------------------------------------------------------------------------------------
def predict_image(model: LandcoverModel, im: LoadedImage, scene: Scene | None = None) -> np.ndarray:
    """Class probabilities (n_classes, rows, cols) of a loaded image, NaN where the image has no data."""
    if im.data.shape[0] != model.n_bands:
        raise ConfigError(f"{im.name} has {im.data.shape[0]} band(s); the model was trained on {model.n_bands}")
    if model.gsd_m and im.camera is not None and scene is not None:
        g = image_gsd_m(im.camera, im.shape, float(np.nanmedian(scene.dem_m)))
        if np.isfinite(g) and not (model.gsd_m / 1.5 <= g <= model.gsd_m * 1.5):
            warnings.warn(
                f"{im.name}: ground sampling {g:.2f} m differs from the training images' "
                f"{model.gsd_m:.2f} m by more than 1.5×; texture features change with scale",
                stacklevel=2,
            )
    F = image_features(im, model.spec, scene)
    return predict_proba(model, F, im.valid)


def project_probability(
    prob: np.ndarray, im: LoadedImage, scene: Scene, name: str = "", window: tuple[int, int, int, int] | None = None
) -> ProjectedView:
    """One image's probability band on the scene grid (camera + surface with occlusion, or an orthoimage's
    geotransform)."""
    if im.is_ortho:
        from ..io.raster import reproject_array

        g = AOIGrid(as_crs(im.crs), im.transform, im.shape[1], im.shape[0])
        v = reproject_array(prob, g, scene.grid, "bilinear")
        obs = np.isfinite(v)
        return ProjectedView(values=v, observed=obs, weight=obs.astype(np.float32), name=name or im.name)
    if im.camera is None:
        raise NoCameraError(f"{im.name} has neither a camera model nor a map georeference; it cannot be projected")
    return project_view(prob, im.camera, scene.grid, scene.surface_m, window=window, name=name or im.name)


def write_probability_image(path: os.PathLike | str, prob: np.ndarray, model: LandcoverModel, im: LoadedImage) -> Path:
    """Image-geometry probability map (float32, one band per class), keeping the image's georeference/RPC."""
    import rasterio

    from ..io.atomic import atomic_path

    arr = np.asarray(prob, np.float32)
    profile = {
        "driver": "GTiff",
        "width": arr.shape[2],
        "height": arr.shape[1],
        "count": arr.shape[0],
        "dtype": "float32",
        "compress": "deflate",
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "nodata": float("nan"),
    }
    rpcs = None
    with rasterio.open(im.path) as src:
        if src.crs is not None:
            profile.update(crs=src.crs, transform=src.transform)
        rpcs = src.rpcs
    if rpcs is not None:
        profile["rpcs"] = rpcs
    with atomic_path(path) as tmp:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with rasterio.open(tmp, "w", **profile) as dst:
                dst.write(arr)
                for i, c in enumerate(model.classes, start=1):
                    dst.set_band_description(i, f"p_{c}")
                dst.update_tags(
                    content="class probabilities (geocd landcover)",
                    method=model.method,
                    classes=",".join(model.classes),
                    source_image=str(im.path),
                )
    side = im.path.with_suffix(".camera.json")
    if im.camera is not None and im.camera.kind == "frame" and side.exists():
        import shutil

        shutil.copyfile(side, Path(path).with_suffix(".camera.json"))
    return Path(path)


def predict_files(
    model_path: os.PathLike | str,
    image_paths: Sequence[str],
    out_dir: os.PathLike | str,
    *,
    cameras: Sequence[str | None] | None = None,
    scene: Scene | None = None,
    class_name: str | None = None,
    prefix: str = "landcover",
    progress=None,
    trust: bool = False,
) -> dict:
    """Probability maps of images (image geometry), and — with a scene — on the grid, combined.

    ``trust``: load a model file that is not on this user's trusted-model list (see :func:`load_model`).
    """
    from ..io.atomic import protect_inputs, write_text_atomic
    from ..io.raster import write_cog

    prog = ensure_progress(progress)
    model = load_model(model_path, trust=trust)
    ci = model.class_index(class_name)
    protect_inputs(model_path, *image_paths)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cams = list(cameras) if cameras else [None] * len(image_paths)
    outputs: dict[str, Path] = {}
    views: list[ProjectedView] = []
    summary: dict = {"class": model.classes[ci], "images": {}}
    for k, (p, c) in enumerate(zip(image_paths, cams)):
        prog(k / max(1, len(image_paths)), f"classifying {Path(p).stem}")
        im = load_image(p, c)
        prob = predict_image(model, im, scene)
        fp = write_probability_image(out / f"{prefix}_{im.name}_proba.tif", prob, model, im)
        outputs[f"proba_{im.name}"] = fp
        s: dict = {"mean_probability": float(np.nanmean(prob[ci]))}
        if scene is not None:
            v = project_probability(prob[ci], im, scene)
            views.append(v)
            s["observed_fraction"] = round(float(v.observed.mean()), 4)
        summary["images"][im.name] = s
    if views:
        mean, weight, count = combine_views(views)
        outputs["ground"] = write_cog(
            out / f"{prefix}_ground.tif",
            {f"p_{model.classes[ci]}": mean, "weight": weight, "views": count.astype(np.float32)},
            scene.grid,
            tags={
                "content": f"probability of {model.classes[ci]!r} projected on the grid "
                "(weighted mean over the views; NaN = unobserved)",
                "method": "geocd landcover predict",
            },
        )
        summary["observed_fraction"] = round(float(np.isfinite(mean).mean()), 4)
    outputs["summary"] = write_text_atomic(out / f"{prefix}_predict.json", json.dumps(summary, indent=2))
    prog(1.0, "done")
    return {"outputs": outputs, "summary": summary}


# ---------------------------------------------------------------------------------------------
# integration
# ---------------------------------------------------------------------------------------------
#: the GP's inputs by name; "xy" stands for the two cell coordinates
INPUTS = ("xy", "dem", "coarse", "buildings")


def gp_inputs(scene: Scene, coarse: np.ndarray | None, use: Sequence[str] = INPUTS) -> dict:
    """Per-cell GP input arrays for the chosen input names."""
    out: dict = {}
    for u in use:
        if u == "xy":
            x, y = scene.grid.xy()
            out["x"], out["y"] = x, y
        elif u == "dem":
            out["dem"] = scene.dem_m
        elif u == "coarse":
            if coarse is None:
                raise ConfigError("the GP input 'coarse' needs a coarse full-cover probability map (--coarse)")
            out["coarse"] = coarse
        elif u == "buildings":
            out["buildings"] = scene.occupancy
        else:
            raise ConfigError(f"unknown GP input {u!r}; known: {INPUTS}")
    return out


def read_on_grid(path: os.PathLike | str, grid: AOIGrid, band: int = 1) -> np.ndarray:
    """A product raster resampled onto the grid (average when coarser cells, NaN = nodata)."""
    from ..io.raster import _open, reproject_band

    with _open(path) as ds:
        if ds.crs is None:
            raise GridError(
                f"{path} has no CRS; give a georeferenced probability map (geocd landcover predict "
                "writes one: *_ground.tif)"
            )
        resampling = "average" if abs(ds.transform.a) < grid.posting_m * 0.75 else "bilinear"
        return reproject_band(ds, band, grid, resampling)


def write_integration(out: Path, prefix: str, scene: Scene, res, detailed: np.ndarray, class_name: str) -> dict:
    from ..io.raster import write_cog

    outputs: dict[str, Path] = {}
    p = np.clip(res.mean, 0.0, 1.0)
    tags = {
        "method": "geocd landcover integrate (GP, ARD kernel, sparse inducing-point prediction)",
        "hyperparameters": json.dumps(res.hyper.to_dict()),
    }
    outputs["probability"] = write_cog(
        out / f"{prefix}_probability.tif",
        {f"p_{class_name}": p},
        scene.grid,
        tags={**tags, "content": f"GP predictive mean of p({class_name}), clipped to [0, 1]"},
    )
    bands = {"sigma": res.sd, "sigma_obs": res.sd_obs}
    if res.sd_cal is not None:
        bands["sigma_calibrated"] = res.sd_cal
    bands.update({"mean_unclipped": res.mean, "detailed": detailed.astype(np.float32)})
    outputs["sigma"] = write_cog(
        out / f"{prefix}_sigma.tif",
        bands,
        scene.grid,
        tags={
            **tags,
            "content": "GP predictive sd of the latent probability (sigma), of a "
            "new observation (sigma_obs) and the latter scaled by "
            "spatial-block cross-validation (sigma_calibrated)",
        },
    )
    return outputs


def integrate_files(
    detailed_path: os.PathLike | str,
    scene: Scene,
    out_dir: os.PathLike | str,
    *,
    coarse_path: os.PathLike | str | None = None,
    use: Sequence[str] | None = None,
    params=None,
    class_name: str = "condition",
    truth_path: os.PathLike | str | None = None,
    truth_values: Sequence[float] | None = None,
    exclude_path: os.PathLike | str | None = None,
    prefix: str = "landcover",
    progress=None,
) -> dict:
    """GP integration of a projected detailed probability (+ a coarse one) over the scene grid; COG products.

    With ``truth_path`` (a raster whose cells equal to one of ``truth_values`` — default: nonzero — hold the
    condition) the thesis's ablation is run and written as a report (JSON + PR figure); ``exclude_path`` (the
    training label layer) keeps labelled cells out of the scores.
    """
    from ..io.atomic import protect_inputs, write_text_atomic
    from .gp import GPParams, integrate
    from .report import ablation, pr_figure

    prog = ensure_progress(progress)
    params = params or GPParams()
    paths = [p for p in (detailed_path, coarse_path, truth_path, exclude_path) if p is not None]
    protect_inputs(*paths)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    det = read_on_grid(detailed_path, scene.grid)
    coarse = read_on_grid(coarse_path, scene.grid) if coarse_path is not None else None
    if use is None:
        use = tuple(
            u for u in INPUTS if (u != "coarse" or coarse is not None) and (u != "buildings" or scene.occupancy.any())
        )
    t0 = time.perf_counter()
    res = integrate(det, gp_inputs(scene, coarse, use), params, progress=sub_progress(prog, 0.0, 0.6))
    outputs = write_integration(out, prefix, scene, res, det, class_name)
    summary: dict = {
        "class": class_name,
        "inputs": list(use),
        "params": params.to_dict(),
        "seconds": round(time.perf_counter() - t0, 2),
        **res.report,
    }
    if truth_path is not None:
        prog(0.65, "ablation against the truth map")
        # the condition is decided on the truth's own grid, then averaged: a class raster is never resampled
        from ..io.raster import read_band, reproject_array

        tr0, tgrid = read_band(truth_path)
        hit = np.isin(np.rint(tr0), np.asarray(truth_values, float)) if truth_values else np.nan_to_num(tr0) > 0.5
        frac = reproject_array(
            np.where(np.isfinite(tr0), hit, np.nan).astype(np.float32),
            tgrid,
            scene.grid,
            "average" if tgrid.posting_m < 0.75 * scene.grid.posting_m else "nearest",
        )
        truth = np.nan_to_num(frac) >= 0.5
        exclude = None
        if exclude_path is not None:
            lab = read_labels(exclude_path)
            if lab.crs is not None:
                cls, _ = rasterize_labels(
                    lab.to_crs(scene.grid.crs), scene.grid.shape, scene.grid.transform, class_list(lab)
                )
                exclude = cls >= 0
        no_truth = ~np.isfinite(frac)
        exclude = no_truth if exclude is None else (exclude | no_truth)
        scores, results = ablation(
            det, coarse, lambda u: gp_inputs(scene, coarse, u), truth, truth_value=frac, exclude=exclude, params=params
        )
        ev = np.ones(truth.shape, bool) if exclude is None else ~exclude
        curves = {}
        if coarse is not None:
            curves["coarse alone"] = (truth[ev], coarse[ev])
        obs = np.isfinite(det) & ev
        curves["detailed alone (observed)"] = (truth[obs], det[obs])
        for n, r in results.items():
            curves[n] = (truth[ev], r.mean[ev])
        outputs["ablation_png"] = out / f"{prefix}_ablation.png"
        pr_figure(outputs["ablation_png"], curves, scores, f"{class_name}: ablation")
        outputs["ablation"] = write_text_atomic(out / f"{prefix}_ablation.json", json.dumps(scores, indent=2))
        summary["ablation"] = {
            k: v.get("f1_at_recall") for k, v in scores.items() if isinstance(v, dict) and "f1_at_recall" in v
        }
    outputs["summary"] = write_text_atomic(out / f"{prefix}_integrate.json", json.dumps(summary, indent=2))
    prog(1.0, "done")
    return {"outputs": outputs, "summary": summary, "result": res}
