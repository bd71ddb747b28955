"""Online update of the volume model from one image (Crispell et al. §V, eqs. 16–26).

For every pixel's ray (the pixel centre), the ray pass (:func:`_kernels.update_rays`)
computes the posterior occlusion probability of each segment (eq. 22) with the
model *before* this image, and accumulates per cell the sums of eq. 25 and the
length-weighted observation and visibility. Then, per cell seen by the image,
α is replaced by ᾱ (eq. 25, clamped) and the appearance mixture of the image's
illumination bin learns the cell's length-weighted mean intensity (weight = the
cell's mean visibility, as boxm2 does). Finally leaves are refined (eq. 26).

The model's arrays change only after every ray has been traced, so a
cancellation (the progress callback raising) leaves the model as it was.
"""

from __future__ import annotations

import datetime as _dt
import time
from dataclasses import asdict, dataclass
from typing import Any, Optional

import numpy as np

from ..errors import CameraError, ConfigError, EmptyDataError
from ..progress import Progress, ensure_progress
from . import _kernels as K
from .rays import check_camera_sees_volume, image_rays
from .refine import coarsen_model, refine_model
from .scene import VolumeModel

#: background density of an intensity seen through the whole volume (uniform on [0, 1])
P_BACKGROUND = 1.0
#: rows of rays traced per step (memory: ~100 bytes per ray)
TILE_PIXELS = 65536
#: an update keeps an image's rays between its two passes up to this many rays (64 bytes each)
RAY_CACHE_MAX_RAYS = 4_000_000


@dataclass(frozen=True)
class UpdateStats:
    """What one update did (also stored in the model's history)."""

    name: str
    sun_bin: int
    rays: int
    segments: int
    cells_updated: int
    leaves_split: int
    leaves_merged: int
    nodes_after: int
    seconds: float

    def to_dict(self) -> dict:
        return asdict(self)


NORMALIZATIONS = ("scale", "percentile", "equalize")


def image_intensity(
    data: np.ndarray, valid: np.ndarray | None = None, bit_depth: int = 8, normalize: str = "scale"
) -> np.ndarray:
    """Image samples → float64 gray intensity in [0, 1] (NaN where invalid).

    Parameters
    ----------
    data : ndarray (bands, rows, cols) or (rows, cols), any numeric dtype
    valid : bool (rows, cols), optional
    bit_depth : int
        Effective bits per sample; integer data are divided by ``2**bit_depth - 1``.
        Float data are taken as already scaled.
    normalize : {"scale", "percentile", "equalize"}
        ``scale``: divide by the bit depth's maximum only. ``percentile``: then map
        the 1st/99th percentiles of the valid pixels to 0.05/0.95 (absorbs sensor
        gain and offset). ``equalize``: each pixel's rank among the valid pixels
        (absorbs any monotone radiometric difference — gamma-encoded aerial RGB
        against linear 11-bit satellite counts — assuming the images see the same
        kind of scene).
    """
    if normalize not in NORMALIZATIONS:
        raise ConfigError(f"normalize must be one of {NORMALIZATIONS}, got {normalize!r}")
    a = np.asarray(data)
    if a.ndim == 3:
        g = a.astype(np.float64).mean(axis=0)
    elif a.ndim == 2:
        g = a.astype(np.float64)
    else:
        raise ConfigError(f"an image must be (rows, cols) or (bands, rows, cols), got shape {a.shape}")
    if np.issubdtype(a.dtype, np.integer):
        g = g / float(2 ** int(bit_depth) - 1)
    if valid is not None:
        g[~np.asarray(valid, bool)] = np.nan
    ok = np.isfinite(g)
    if normalize == "percentile" and ok.any():
        p1, p99 = np.percentile(g[ok], [1.0, 99.0])
        if p99 > p1:
            g = 0.05 + 0.9 * (g - p1) / (p99 - p1)
    elif normalize == "equalize" and ok.any():
        v = g[ok]
        srt = np.sort(v)
        rank = 0.5 * (np.searchsorted(srt, v, "left") + np.searchsorted(srt, v, "right"))
        g[ok] = rank / v.size
    return np.clip(g, 0.0, 1.0)


def _check_image(model: VolumeModel, intensity: np.ndarray, camera: Any, name: str) -> np.ndarray:
    img = np.asarray(intensity, dtype=np.float64)
    if img.ndim != 2:
        raise ConfigError(f"{name}: the intensity image must be 2-D (rows, cols), got shape {img.shape}")
    if not np.isfinite(img).any():
        raise EmptyDataError(f"{name} has no valid pixel")
    w, h = getattr(camera, "width", None), getattr(camera, "height", None)
    if w is not None and h is not None and (int(w), int(h)) != (img.shape[1], img.shape[0]):
        raise CameraError(
            f"{name} is {img.shape[1]}x{img.shape[0]} pixels but its camera is for {w}x{h}; give the camera of this "
            "image (a crop needs camera.cropped(...))"
        )
    return img


class RayScratch:
    """Per-call scratch buffers of the per-ray kernels (sized by :func:`_kernels.max_segments`)."""

    def __init__(self, geo: np.ndarray):
        n = K.max_segments(geo)
        self.seg_cell = np.empty(n, dtype=np.int64)
        self.seg_len = np.empty(n, dtype=np.float64)
        self.seg_t = np.empty(n, dtype=np.float64)
        self.a = np.empty(n, dtype=np.float64)
        self.b = np.empty(n, dtype=np.float64)
        self.c = np.empty(n, dtype=np.float64)
        self.d = np.empty(n, dtype=np.float64)


def update_model(
    model: VolumeModel,
    intensity: np.ndarray,
    camera: Any,
    *,
    sun: tuple[float, float] | None = None,
    name: str = "",
    stride: int = 1,
    supersample: int = 1,
    cell_mean: bool = True,
    refine: bool | None = None,
    ray_cache: dict | None = None,
    progress: Optional[Progress] = None,
) -> UpdateStats:
    """Update ``model`` in place with one image.

    Parameters
    ----------
    model : VolumeModel
    intensity : ndarray float (rows, cols)
        Gray intensity in [0, 1], NaN where invalid (see :func:`image_intensity`).
    camera : geocd.camera.Camera
        The image's camera (any kind).
    sun : (azimuth_deg, elevation_deg), optional
        Sun position of the image; selects (or opens) the illumination bin.
        None: a single illumination for all images.
    name : str
        Recorded in the model's history.
    stride : int
        Trace every ``stride``-th pixel in each direction (1 = all pixels).
    supersample : int
        k×k rays per traced pixel (k > 1 when the finest cells are smaller than
        the pixels' ground footprint, so that every cell is crossed).
    cell_mean : bool
        Evaluate each cell's appearance at the cell's length-weighted mean
        observation in this image (boxm2's practice, an extra ray pass) rather
        than at each pixel's intensity (the paper's eq. 20); see
        :func:`geocd.volume._kernels.update_rays`.
    refine : bool, optional
        Run adaptive refinement afterwards (default: ``model.params.refine``).
    ray_cache : dict, optional
        Where this image's rays are kept between calls: a caller that updates the model with the same image
        several times (training passes) passes the same dict each time and the rays are computed once
        (about 64 bytes per ray; the rays depend on the camera and the model's frame, not on its cells).
        Within one call the two ray passes share their rays whenever the image holds at most
        :data:`RAY_CACHE_MAX_RAYS` rays.
    progress : callable, optional
        ``progress(fraction, message)``; may raise CancelledError (the model is
        then unchanged).

    Raises
    ------
    CameraError
        The camera gives no finite rays (e.g. NaN parameters) or does not match the image size.
    NoOverlapError
        The image does not see the volume.
    """
    t_start = time.perf_counter()
    prog = ensure_progress(progress)
    img = _check_image(model, intensity, camera, name or "the image")
    rows, cols = img.shape
    geom = model.geometry
    check_camera_sees_volume(camera, geom, cols, rows, name or "the image")
    stride = max(int(stride), 1)
    b = model.sun_bin(sun, create=True)
    try:
        n = model.n_nodes
        acc_len = np.zeros(n)
        acc_log = np.zeros(n)
        acc_obs = np.zeros(n)
        acc_vis = np.zeros(n)
        geo = geom.geo_array()
        lo, hi = geom.box_lo, geom.box_hi
        sc = RayScratch(geo)
        ss = max(int(supersample), 1)
        tile_rows = max(stride, (TILE_PIXELS // max(cols * ss * ss // stride, 1)) * stride)
        n_rays = 0
        n_segs = 0
        tiles = list(range(0, rows, tile_rows))
        n_rays_image = len(range(0, rows, stride)) * len(range(0, cols, stride)) * ss * ss
        if ray_cache is None and cell_mean and n_rays_image <= RAY_CACHE_MAX_RAYS:
            ray_cache = {}  # shared by this call's two passes
        key = (
            id(camera),
            geom.frame.lon0,
            geom.frame.lat0,
            geom.frame.h0,
            tuple(geom.z_range_enu),
            rows,
            cols,
            stride,
            ss,
            tile_rows,
        )
        if ray_cache is not None and ray_cache.get("key") != key:
            ray_cache.clear()
            ray_cache["key"] = key
        n_steps = 2 * len(tiles) if cell_mean else len(tiles)
        step = 0
        cell_pa = np.zeros(0)
        passes = ("mean", "bayes") if cell_mean else ("bayes",)
        for which in passes:
            if which == "bayes" and cell_mean:
                with np.errstate(invalid="ignore", divide="ignore"):
                    cell_obs = np.where(acc_len > 0, acc_obs / acc_len, np.nan)
                # each cell's density at its mean observation, once per cell rather than per ray segment
                cell_pa = np.empty(n)
                K.mog_density_cells(model.app, b, cell_obs, model.params.appearance_prior_weight, cell_pa)
                acc_len[:] = 0.0
                acc_obs[:] = 0.0
            for r0 in tiles:
                r1 = min(rows, r0 + tile_rows)
                if ray_cache is not None and r0 in ray_cache:
                    o, d, rr, cc = ray_cache[r0]
                else:
                    o, d, rr, cc = image_rays(camera, geom, r0, r1, cols, stride, ss)
                    if ray_cache is not None:
                        ray_cache[r0] = (o, d, rr, cc)
                obs = img[rr, cc]
                ok = np.isfinite(obs) & np.isfinite(o[:, 0])
                obs = np.where(ok, obs, np.nan)
                if which == "mean":
                    n_segs += K.seglen_rays(
                        o,
                        d,
                        obs,
                        lo,
                        hi,
                        geo,
                        model.block_root,
                        model.child,
                        acc_len,
                        acc_obs,
                        sc.seg_cell,
                        sc.seg_len,
                        sc.seg_t,
                    )
                else:
                    n_rays += int(ok.sum())
                    n_segs += K.update_rays(
                        o,
                        d,
                        obs,
                        cell_pa,
                        lo,
                        hi,
                        geo,
                        model.block_root,
                        model.child,
                        model.alpha,
                        model.app,
                        b,
                        P_BACKGROUND,
                        model.params.appearance_prior_weight,
                        acc_len,
                        acc_log,
                        acc_obs,
                        acc_vis,
                        sc.seg_cell,
                        sc.seg_len,
                        sc.seg_t,
                        sc.a,
                        sc.b,
                        sc.c,
                        sc.d,
                    )
                step += 1
                prog(0.9 * step / n_steps, f"update {name}: {which} pass, rows {r1}/{rows}")
    except BaseException:
        if model.sun_bins and model.sun_bins[b][2] == 0 and b == len(model.sun_bins) - 1:
            model.sun_bins.pop()  # a bin opened for this image and never trained
        raise
    p = model.params
    # from here on the model changes; nothing below calls back into user code
    n_upd = K.finalize_update(
        acc_len,
        acc_log,
        acc_obs,
        acc_vis,
        model.alpha,
        model.app,
        b,
        p.alpha_min,
        p.alpha_max,
        p.sigma_init,
        p.sigma_min,
        p.match_sigmas,
        p.min_obs_weight,
    )
    model.sun_bins[b][2] += 1
    split = 0
    merged = 0
    if p.refine if refine is None else refine:
        if p.coarsen:
            merged = coarsen_model(model)
        split = refine_model(model)
    stats = UpdateStats(
        name=name,
        sun_bin=b,
        rays=n_rays,
        segments=int(n_segs),
        cells_updated=int(n_upd),
        leaves_split=split,
        leaves_merged=merged,
        nodes_after=model.n_nodes,
        seconds=time.perf_counter() - t_start,
    )
    entry = stats.to_dict()
    entry["time_utc"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    if sun is not None:
        entry["sun"] = [float(sun[0]), float(sun[1])]
    model.history.append(entry)
    prog(1.0, f"update {name}: {n_upd} cells, {split} split")
    return stats
