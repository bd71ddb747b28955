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
        "format": FORMAT,
        "version": VERSION,
        "geometry": model.geometry.to_dict(),
        "params": model.params.to_dict(),
        "sun_bins": model.sun_bins,
        "history": model.history,
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
    """Read a model written by :func:`save_model`, checking it before any kernel walks it.

    Besides the metadata, the arrays are checked against each other (shapes, dtypes), the octree
    is checked to be a tree the traversal kernels can walk (every child pointer ``-1`` or the first
    of 8 nodes after its parent, no node with two parents, levels one deeper per step and at most
    ``max_depth``, block roots in range) and the values are checked to be finite: a damaged model
    is an error here, never an out-of-bounds read or an endless loop in a kernel.

    Raises
    ------
    InputFileNotFoundError
        No model at ``path``.
    UnsupportedFormatError
        The folder is not a geocd volume model, or is from a newer version, or is damaged (a file
        missing, truncated or garbled, arrays inconsistent, an invalid tree, non-finite values);
        the message names the file.
    """
    p = Path(path)
    meta_path = p / "model.json"
    if not meta_path.is_file():
        raise InputFileNotFoundError(
            f"no volume model at {p} (model.json missing); create one with 'geocd volume update --create'"
        )
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise UnsupportedFormatError(f"{meta_path} is not valid JSON ({exc}); the model is damaged") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        fmt = meta.get("format") if isinstance(meta, dict) else None
        raise UnsupportedFormatError(f"{p} is not a geocd volume model (format {fmt!r})")
    try:
        version = int(meta.get("version", 0))
        geom = VolumeGeometry.from_dict(meta["geometry"])
        params = VolumeParams.from_dict(meta["params"])
        wanted = {k: meta["arrays"][k] for k in ARRAYS}
        sun_bins = [list(b) for b in meta.get("sun_bins", [])]
        history = list(meta.get("history", []))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise UnsupportedFormatError(
            f"{meta_path} is damaged ({type(exc).__name__}: {exc}); rebuild the model "
            "with 'geocd volume update --create'"
        ) from exc
    if version > VERSION:
        raise UnsupportedFormatError(f"{p} was written by a newer geocd (version {meta['version']}); upgrade geocd")
    _check_geometry(meta_path, geom)
    arrays = {}
    for k in ARRAYS:
        f = p / f"{k}.npy"
        if not f.is_file():
            raise UnsupportedFormatError(f"{p} lacks {k}.npy; the model is incomplete")
        a = _load_npy(f, mmap)
        want = wanted[k]
        if (
            not isinstance(want, dict)
            or list(a.shape) != list(want.get("shape", []))
            or str(a.dtype) != want.get("dtype")
        ):
            raise UnsupportedFormatError(
                f"{f} has shape {a.shape} {a.dtype}, model.json says {want}; the model is damaged"
            )
        arrays[k] = a if mmap else np.ascontiguousarray(a)
    _check_arrays(p, geom, params, arrays, sun_bins, history)
    return VolumeModel(
        geom,
        params,
        arrays["block_root"],
        arrays["child"],
        arrays["level"],
        arrays["alpha"],
        arrays["app"],
        sun_bins,
        history,
    )


#: the dtype and number of dimensions of each array (the kernels' types)
_ARRAY_TYPES = {
    "block_root": (np.int32, 3),
    "child": (np.int32, 1),
    "level": (np.uint8, 1),
    "alpha": (np.float32, 1),
    "app": (np.float32, 4),
}
#: nodes checked per step (bounds the memory of the checks on a large model)
_CHUNK = 1 << 20


def _damaged(path: Path, what: str) -> UnsupportedFormatError:
    return UnsupportedFormatError(
        f"the volume model {path} is damaged: {what}; rebuild it with "
        "'geocd volume update --create' (or restore a copy)"
    )


def _load_npy(f: Path, mmap: bool) -> np.ndarray:
    """One ``.npy`` file, its header checked against the file size first (a truncated file is an error)."""
    fmt = np.lib.format
    try:
        with open(f, "rb") as fh:
            major, _minor = fmt.read_magic(fh)
            read_header = fmt.read_array_header_1_0 if major == 1 else fmt.read_array_header_2_0
            shape, _fortran, dtype = read_header(fh)
            data_b = os.fstat(fh.fileno()).st_size - fh.tell()
        if dtype.hasobject:
            raise ValueError("it holds Python objects")
        need_b = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if need_b != data_b:
            raise ValueError(f"its header promises {need_b} bytes of {dtype} {tuple(shape)} but it holds {data_b}")
        return np.load(f, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, OSError, EOFError, TypeError) as exc:
        raise UnsupportedFormatError(
            f"{f} is truncated or not a valid .npy file ({exc}); the volume model is "
            "damaged: rebuild it with 'geocd volume update --create' (or restore a "
            "copy)"
        ) from exc


def _check_geometry(meta_path: Path, geom: VolumeGeometry) -> None:
    vals = [*geom.origin_enu, geom.block_size_m, *geom.aoi_bounds, geom.frame.lon0, geom.frame.lat0, geom.frame.h0]
    if not np.all(np.isfinite(vals)):
        raise _damaged(meta_path, f"the geometry holds non-finite values ({geom.to_dict()})")
    l, b, r, t = geom.aoi_bounds
    if not (l < r and b < t):
        raise _damaged(meta_path, f"the AOI bounds {geom.aoi_bounds} are empty or inverted")
    if not (-180.0 <= geom.frame.lon0 <= 180.0 and -90.0 <= geom.frame.lat0 <= 90.0):
        raise _damaged(meta_path, f"the ENU origin (lon {geom.frame.lon0}, lat {geom.frame.lat0}) is off the Earth")


def _check_arrays(
    p: Path, geom: VolumeGeometry, params: VolumeParams, arrays: dict, sun_bins: list, history: list
) -> None:
    """The arrays form a tree the kernels can walk, with finite values (see :func:`load_model`)."""
    from .scene import N_FIELDS, N_MODES, NOBS, SIGMA, WEIGHT

    for k, (dtype, ndim) in _ARRAY_TYPES.items():
        a = arrays[k]
        if a.dtype != np.dtype(dtype) or a.ndim != ndim:
            raise _damaged(p / f"{k}.npy", f"it is {a.ndim}-D {a.dtype}, the model needs {ndim}-D {np.dtype(dtype)}")
    child, level, alpha, app, root = (arrays[k] for k in ("child", "level", "alpha", "app", "block_root"))
    n = child.shape[0]
    if n == 0 or not all(arrays[k].shape[0] == n for k in ("level", "alpha", "app")):
        raise _damaged(p, "the per-cell arrays (child, level, alpha, app) disagree in length")
    if tuple(root.shape) != tuple(geom.n_blocks):
        raise _damaged(p / "block_root.npy", f"its shape {root.shape} is not n_blocks {geom.n_blocks}")
    if tuple(app.shape[1:]) != (params.n_bins, N_MODES, N_FIELDS):
        raise _damaged(
            p / "app.npy",
            f"its shape {app.shape} is not (cells, {params.n_bins} illumination bins, {N_MODES}, {N_FIELDS})",
        )
    if len(sun_bins) > params.n_bins or any(
        len(b) != 3 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in b) for b in sun_bins
    ):
        raise _damaged(
            p / "model.json", f"sun_bins {sun_bins} are not up to {params.n_bins} (azimuth, elevation, count) triples"
        )
    if not all(isinstance(h, dict) for h in history):
        raise _damaged(p / "model.json", "its history is not a list of records")
    # block roots: distinct nodes of level 0
    roots = np.asarray(root, dtype=np.int64).ravel()
    if roots.min() < 0 or roots.max() >= n:
        raise _damaged(p / "block_root.npy", f"a block root is outside the {n} nodes ({roots.min()} … {roots.max()})")
    if np.unique(roots).size != roots.size:
        raise _damaged(p / "block_root.npy", "two blocks share a root node")
    if np.any(level[roots] != 0):
        raise _damaged(p / "level.npy", "a block root is not at level 0")
    if int(level.max()) > geom.max_depth:
        raise _damaged(
            p / "level.npy", f"a node is at level {int(level.max())}, deeper than max_depth {geom.max_depth}"
        )
    # child pointers: -1, or the first of 8 nodes after the parent (the format builds children after their parent,
    # so this rules out cycles); the 8 are one level deeper, and no node has two parents
    starts = []
    for s in range(0, n, _CHUNK):
        c = child[s : s + _CHUNK].astype(np.int64)
        node = np.arange(s, s + c.size, dtype=np.int64)
        inner = c >= 0
        bad = (c < -1) | (inner & ((c <= node) | (c + 8 > n)))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise _damaged(
                p / "child.npy",
                f"node {s + i} points to child {int(c[i])}, which is neither -1 nor the "
                f"first of 8 nodes after it among the {n}",
            )
        lv = level[s : s + c.size][inner]
        if np.any(lv >= geom.max_depth):
            raise _damaged(p / "child.npy", f"a node at level max_depth {geom.max_depth} has children")
        ci = c[inner]
        for k in range(8):
            if np.any(level[ci + k] != lv + 1):
                raise _damaged(p / "level.npy", "a node's children are not one level below it")
        starts.append(ci)
    starts = np.sort(np.concatenate(starts))
    if starts.size:
        if np.any(np.diff(starts) < 8):
            raise _damaged(p / "child.npy", "two nodes share children")
        j = np.searchsorted(starts, roots, side="right") - 1
        if np.any((j >= 0) & (roots < starts[np.maximum(j, 0)] + 8)):
            raise _damaged(p / "block_root.npy", "a block root is also a child node")
    # values: finite; densities, spreads, weights and counts not negative
    for s in range(0, n, _CHUNK):
        a = alpha[s : s + _CHUNK]
        if not np.all(np.isfinite(a)) or np.any(a < 0):
            raise _damaged(p / "alpha.npy", "it holds non-finite or negative occlusion densities")
        ap = app[s : s + _CHUNK]
        if not np.all(np.isfinite(ap)):
            raise _damaged(p / "app.npy", "it holds non-finite appearance values")
        if np.any(ap[..., [SIGMA, WEIGHT, NOBS]] < 0):
            raise _damaged(p / "app.npy", "it holds negative appearance spreads, weights or counts")


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
SUN_TAGS = (
    ("SUN_AZIMUTH", "SUN_ELEVATION"),
    ("MEANSUNAZ", "MEANSUNEL"),
    ("IMD_IMAGE_1_MEANSUNAZ", "IMD_IMAGE_1_MEANSUNEL"),
)


def sun_from_tags(tags: dict) -> tuple[float, float] | None:
    """Sun (azimuth, elevation) degrees from image metadata, or None."""
    for ka, ke in SUN_TAGS:
        if ka in tags and ke in tags:
            try:
                return float(tags[ka]), float(tags[ke])
            except ValueError:
                continue
    return None


def read_view(
    image_path: os.PathLike | str,
    camera_path: os.PathLike | str | None = None,
    *,
    name: str = "",
    sun: tuple[float, float] | None = None,
    normalize: str = "equalize",
) -> View:
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
    return View(
        name or Path(image_path).stem,
        image_intensity(img.data, img.valid, img.bit_depth, normalize),
        cam,
        s,
        str(image_path),
    )


def read_shadow_dsm(path: os.PathLike | str, grid: Any) -> tuple[np.ndarray, Any]:
    """A DSM file (any CRS and vertical datum GDAL reads) as ellipsoidal heights on ``grid`` (an AOIGrid in the
    model's CRS): the ``shadow_dsm`` pair of :func:`geocd.volume.detect_change`."""
    from ..io.raster import read_dem

    return read_dem(path, grid=grid).to_ellipsoidal().height_m, grid


def disk_bytes(path: os.PathLike | str) -> int:
    """Bytes of a saved model folder."""
    return sum(f.stat().st_size for f in Path(path).iterdir() if f.is_file())


def geometry_from_manifest(
    manifest: Any,
    *,
    finest_cell_m: float = 0.5,
    max_depth: int = 3,
    above_m: float = 30.0,
    below_m: float = 3.0,
    posting_m: float | None = None,
):
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
        raise ManifestError(
            "the volume model needs the manifest's AOI (aoi: crs, bounds, posting_m); add it to scene.yaml"
        )
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
    geom = geometry_for_aoi(
        grid, z_min_m=z0 - below_m, z_max_m=z1 + above_m, finest_cell_m=finest_cell_m, max_depth=max_depth
    )
    return geom, grid
