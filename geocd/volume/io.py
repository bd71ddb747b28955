"""Save and load a volume model: a folder of ``.npy`` arrays + ``model.json``.

``model.json`` holds the format version, the geometry (CRS of the AOI, ENU
origin, block layout), the parameters, the illumination bins, the history of
images used, and per-array shapes/dtypes for a consistency check on load.

Saving writes a new folder next to the target and swaps it in
(:func:`geocd.io.atomic.atomic_dir`): a crash or a cancel mid-save, or
mid-update, never leaves a half-written model in place of a good one.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputFileNotFoundError, OutputError, UnsupportedFormatError
from ..io.atomic import atomic_dir
from .scene import VolumeGeometry, VolumeModel, VolumeParams

FORMAT = "geocd-volume"
VERSION = 1
ARRAYS = ("block_root", "child", "level", "alpha", "app")


def save_model(model: VolumeModel, path: os.PathLike | str) -> Path:
    """Write ``model`` to the folder ``path`` atomically (replacing a previous model there).

    Raises
    ------
    OutputError
        ``path`` exists and is not a volume model folder (never clobbered).
    """
    target = Path(path)
    if target.exists() and not (target.is_dir() and (target / "model.json").is_file()):
        raise OutputError(f"{target} exists and is not a geocd volume model; choose another output path")
    meta = {
        "format": FORMAT, "version": VERSION,
        "geometry": model.geometry.to_dict(), "params": model.params.to_dict(),
        "sun_bins": model.sun_bins, "history": model.history,
        "arrays": {k: {"shape": list(getattr(model, k).shape), "dtype": str(getattr(model, k).dtype)} for k in ARRAYS},
        "size": model.size_report(),
    }
    try:
        with atomic_dir(target) as tmp:
            for k in ARRAYS:
                np.save(tmp / f"{k}.npy", np.ascontiguousarray(getattr(model, k)), allow_pickle=False)
            (tmp / "model.json").write_text(json.dumps(meta, indent=1, default=_json_default), encoding="utf-8")
    except OSError as exc:
        raise OutputError(f"cannot write the volume model to {target}: {exc}") from exc
    return target


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def load_model(path: os.PathLike | str, mmap: bool = False) -> VolumeModel:
    """Read a model written by :func:`save_model`.

    Raises
    ------
    InputFileNotFoundError
        No model at ``path``.
    UnsupportedFormatError
        The folder is not a geocd volume model, or is from a newer version, or
        its arrays do not match its metadata.
    """
    p = Path(path)
    meta_path = p / "model.json"
    if not meta_path.is_file():
        raise InputFileNotFoundError(f"no volume model at {p} (model.json missing); create one with "
                                     "'geocd volume update --create'")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise UnsupportedFormatError(f"{meta_path} is not valid JSON ({exc}); the model is damaged") from exc
    if meta.get("format") != FORMAT:
        raise UnsupportedFormatError(f"{p} is not a geocd volume model (format {meta.get('format')!r})")
    if int(meta.get("version", 0)) > VERSION:
        raise UnsupportedFormatError(f"{p} was written by a newer geocd (version {meta['version']}); upgrade geocd")
    arrays = {}
    for k in ARRAYS:
        f = p / f"{k}.npy"
        if not f.is_file():
            raise UnsupportedFormatError(f"{p} lacks {k}.npy; the model is incomplete")
        a = np.load(f, mmap_mode="r" if mmap else None, allow_pickle=False)
        want = meta["arrays"][k]
        if list(a.shape) != list(want["shape"]) or str(a.dtype) != want["dtype"]:
            raise UnsupportedFormatError(f"{f} has shape {a.shape} {a.dtype}, model.json says {want}; the model is "
                                         "damaged")
        arrays[k] = a if mmap else np.ascontiguousarray(a)
    geom = VolumeGeometry.from_dict(meta["geometry"])
    params = VolumeParams.from_dict(meta["params"])
    n = arrays["child"].shape[0]
    if not all(arrays[k].shape[0] == n for k in ("level", "alpha", "app")):
        raise UnsupportedFormatError(f"{p}: per-cell arrays disagree in length; the model is damaged")
    if tuple(arrays["block_root"].shape) != tuple(geom.n_blocks):
        raise UnsupportedFormatError(f"{p}: block_root shape {arrays['block_root'].shape} does not match "
                                     f"n_blocks {geom.n_blocks}; the model is damaged")
    return VolumeModel(geom, params, arrays["block_root"], arrays["child"], arrays["level"], arrays["alpha"],
                       arrays["app"], [list(b) for b in meta.get("sun_bins", [])], list(meta.get("history", [])))


@dataclass
class View:
    """One image ready for the volume model.

    Attributes
    ----------
    name : str
    intensity : float64 (rows, cols) gray in [0, 1], NaN invalid
    camera : geocd.camera.Camera
    sun : (azimuth_deg, elevation_deg) or None
    path : str
    """

    name: str
    intensity: np.ndarray
    camera: Any
    sun: tuple[float, float] | None
    path: str = ""


#: image metadata keys holding the sun position (geocd synth; DigitalGlobe IMD names as GDAL exposes them)
SUN_TAGS = (("SUN_AZIMUTH", "SUN_ELEVATION"), ("MEANSUNAZ", "MEANSUNEL"), ("IMD_IMAGE_1_MEANSUNAZ",
                                                                          "IMD_IMAGE_1_MEANSUNEL"))


def sun_from_tags(tags: dict) -> tuple[float, float] | None:
    """Sun (azimuth, elevation) degrees from image metadata, or None."""
    for ka, ke in SUN_TAGS:
        if ka in tags and ke in tags:
            try:
                return float(tags[ka]), float(tags[ke])
            except ValueError:
                continue
    return None


def read_view(image_path: os.PathLike | str, camera_path: os.PathLike | str | None = None, *, name: str = "",
              sun: tuple[float, float] | None = None, normalize: str = "equalize") -> View:
    """Read an image, its camera (any kind, via :func:`geocd.io.load_camera`) and its sun position.

    Parameters
    ----------
    sun : optional override of the sun position read from the image's metadata
    normalize : see :func:`geocd.volume.image_intensity`
    """
    import rasterio

    from ..io.cameras import load_camera
    from ..io.raster import read_image
    from .update import image_intensity

    img = read_image(image_path)
    cam = load_camera(image_path, camera_path)
    tags = dict(img.tags)
    try:
        import warnings

        from rasterio.errors import NotGeoreferencedWarning

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            ds = rasterio.open(image_path)
        with ds:
            tags.update(ds.tags())
            for dom in ("IMD", "IMAGERY"):
                try:
                    tags.update({f"{k}": v for k, v in ds.tags(ns=dom).items()})
                except Exception:  # pragma: no cover - absent domains
                    pass
    except Exception:  # pragma: no cover - read_image already opened it
        pass
    s = sun if sun is not None else sun_from_tags(tags)
    return View(name or Path(image_path).stem, image_intensity(img.data, img.valid, img.bit_depth, normalize), cam, s,
                str(image_path))


def read_shadow_dsm(path: os.PathLike | str, grid: Any) -> tuple[np.ndarray, Any]:
    """A DSM file (any CRS and vertical datum GDAL reads) as ellipsoidal heights on ``grid`` (an AOIGrid in the
    model's CRS): the ``shadow_dsm`` pair of :func:`geocd.volume.detect_change`."""
    from ..io.raster import read_dem

    return read_dem(path, grid=grid).to_ellipsoidal().height_m, grid


def disk_bytes(path: os.PathLike | str) -> int:
    """Bytes of a saved model folder."""
    return sum(f.stat().st_size for f in Path(path).iterdir() if f.is_file())


def geometry_from_manifest(manifest: Any, *, finest_cell_m: float = 0.5, max_depth: int = 3,
                           above_m: float = 30.0, below_m: float = 3.0, posting_m: float | None = None):
    """The volume box of a manifest's AOI: from the prior DEM's range (``below_m`` under its
    minimum to ``above_m`` over its maximum, ellipsoidal), or from the images' RPC height
    range when the manifest has no DEM.

    Returns
    -------
    (VolumeGeometry, AOIGrid)
    """
    from ..errors import ManifestError
    from ..geodesy import AOIGrid
    from ..io.raster import read_dem
    from .scene import geometry_for_aoi

    a = manifest.aoi
    if a is None or a.bounds is None or a.crs is None:
        raise ManifestError("the volume model needs the manifest's AOI (aoi: crs, bounds, posting_m); add it to "
                            "scene.yaml")
    grid = AOIGrid.from_bounds(*a.bounds, posting_m or a.posting_m or finest_cell_m, a.crs)
    if manifest.dem is not None:
        dem = read_dem(manifest.dem.path, grid=grid, vertical_datum=manifest.dem.vertical_datum)
        dem = dem.to_ellipsoidal()
        z0, z1 = float(np.nanmin(dem.height_m)), float(np.nanmax(dem.height_m))
    else:
        from ..io.cameras import load_camera

        spans = []
        for e in manifest.epochs:
            for im in e.images:
                hr = load_camera(im.path, im.camera).height_range()
                if hr is not None:
                    spans.append(hr)
        if not spans:
            raise ManifestError("the manifest has no DEM and no image gives a height range; add 'dem:' to scene.yaml")
        z0 = float(np.median([s[0] for s in spans]))
        z1 = float(np.median([s[1] for s in spans]))
        above_m = 0.0
    geom = geometry_for_aoi(grid, z_min_m=z0 - below_m, z_max_m=z1 + above_m, finest_cell_m=finest_cell_m,
                            max_depth=max_depth)
    return geom, grid
