"""The 2-D screen of one image pair: grid features → d_g → pixels → superpixels → exclusions.

Sakurada's thesis, ch. 4 (eqs. 4.1–4.4), for overhead images on one grid:

1. Both images are split into cells of ``cell_px`` pixels; each cell gets a normalised
   feature ``x_g`` (:mod:`geocd.screen.features`); ``d_g = |x_g^A − x_g^B|`` (4.1).
2. ``d_g`` is spread onto the pixels (bilinear between cell centres, or nearest).
3. Each image is cut into superpixels (Felzenszwalb's graph segmentation as in the thesis,
   or SLIC); the pixel values are averaged per superpixel of each image (4.2) and the
   larger of the two images' averages is kept (4.3).
4. The overhead analogue of the thesis's sky/ground exclusion (4.4): the dissimilarity is
   set to 0 where **both** images say vegetation (NDVI with a near-infrared band, else the
   excess-green index of RGB; the threshold is each image's own Otsu split, so a dormant
   season's weaker green is still split from the rest) or where both say cast shadow
   (luminance under half the image's median: direct sun is several times brighter than
   sky light). ``"either"`` rules (vegetation or shadow in one image suffices) are there
   for scenes where a season or a sun change is known to dominate.

Arrays in, arrays out; the threshold is applied by the caller (:mod:`geocd.screen.threshold`).
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..errors import ConfigError, GridError
from ..params import ParamsMixin
from .features import FeatureSpec, GridFeature, grey

SUPERPIXELS = ("felzenszwalb", "slic", "none")
RULES = ("both", "either", "off")
#: bits of the ``excluded`` band
EXCL_VEGETATION = 1
EXCL_SHADOW = 2


@dataclass(frozen=True)
class ScreenParams(ParamsMixin):
    """How to screen a pair.

    Attributes
    ----------
    feature : FeatureSpec
    superpixels : "felzenszwalb" (thesis) | "slic" | "none"
    segment_m : typical superpixel size in metres (Felzenszwalb's minimum size is a quarter
        of its area, its scale ``fz_scale``; SLIC makes segments of about this side). 3 m, a
        small room or a car: segments must not straddle two buildings.
    fz_scale, fz_sigma : Felzenszwalb's scale and Gaussian σ (px)
    spread : "bilinear" | "nearest" — how ``d_g`` reaches the pixels
    vegetation, shadow : exclusion rules "both" (thesis) | "either" | "off"
    min_valid : fraction of a cell's pixels that must be valid for the cell to count
    """

    _kind = "screen"

    feature: FeatureSpec = FeatureSpec()
    superpixels: str = "felzenszwalb"
    segment_m: float = 3.0
    fz_scale: float = 100.0
    fz_sigma: float = 0.8
    spread: str = "bilinear"
    vegetation: str = "both"
    shadow: str = "both"
    min_valid: float = 0.5

    def __post_init__(self) -> None:
        if isinstance(self.feature, dict):
            object.__setattr__(self, "feature", FeatureSpec.from_dict(self.feature))
        if self.superpixels not in SUPERPIXELS:
            raise ConfigError(f"superpixels must be one of {SUPERPIXELS}, got {self.superpixels!r}")
        if self.vegetation not in RULES or self.shadow not in RULES:
            raise ConfigError(f"vegetation and shadow rules must be one of {RULES}")
        if self.spread not in ("bilinear", "nearest"):
            raise ConfigError(f"spread must be bilinear or nearest, got {self.spread!r}")
        if not self.segment_m > 0:
            raise ConfigError(f"segment_m must be > 0, got {self.segment_m}")

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["feature"] = self.feature.to_dict()
        return d


@dataclass
class ScreenResult:
    """The screen of one pair on one grid (all arrays (rows, cols) unless said).

    Attributes
    ----------
    dissimilarity : float32, final d (superpixel max, exclusions applied); NaN = not valid
    grid_dissimilarity : float32, d_g spread to pixels (before superpixels)
    cell_dissimilarity : float32 (rows // cell, cols // cell), d_g itself
    excluded : uint8 bits (1 vegetation in both / either, 2 shadow)
    valid : bool, both images valid
    cell_px : int
    unrelated_d : median distance between the descriptors of two different, random cells (of either
        date): what "entirely different" measures with this feature on this scene. A cell changed over
        half its area sits near or above half of it (the floor of the no-change threshold rule).
    notes : list of str
    """

    dissimilarity: np.ndarray
    grid_dissimilarity: np.ndarray
    cell_dissimilarity: np.ndarray
    excluded: np.ndarray
    valid: np.ndarray
    cell_px: int
    unrelated_d: float = float("nan")
    notes: list[str] = field(default_factory=list)


def unrelated_distance(
    xa: np.ndarray, xb: np.ndarray, valid_cells: np.ndarray | None = None, n: int = 4000, seed: int = 0
) -> float:
    """Median |x_i − x_j| over random pairs of different cells drawn from both dates' descriptors."""
    f = np.concatenate([xa.reshape(-1, xa.shape[-1]), xb.reshape(-1, xb.shape[-1])])
    if valid_cells is not None:
        v = np.concatenate([valid_cells.ravel(), valid_cells.ravel()])
        f = f[v]
    if len(f) < 4:
        return float("nan")
    rng = np.random.default_rng(seed)
    i = rng.integers(0, len(f), n)
    j = rng.integers(0, len(f), n)
    keep = i != j
    return float(np.median(np.linalg.norm(f[i[keep]] - f[j[keep]], axis=1)))


# ---------------------------------------------------------------------------------------------
# images
# ---------------------------------------------------------------------------------------------
def normalise_image(
    image: np.ndarray, valid: np.ndarray | None = None, lo_pct: float = 1.0, hi_pct: float = 99.0
) -> tuple[np.ndarray, np.ndarray]:
    """Stretch each band to 0–1 on its own 1–99 % of the valid pixels; invalid pixels filled with 0.5.

    Any dtype and bit depth (11-bit pan, 8-bit RGB, float reflectance) lands on one scale, so a
    gain or offset between the dates is not a dissimilarity.

    Returns
    -------
    (bands, rows, cols) float32, valid bool (rows, cols)
    """
    a = np.asarray(image, np.float32)
    if a.ndim == 2:
        a = a[None]
    ok = np.all(np.isfinite(a), axis=0)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    out = np.empty_like(a)
    for k in range(a.shape[0]):
        v = a[k][ok]
        if v.size < 16:
            out[k] = 0.5
            continue
        lo, hi = np.percentile(v, [lo_pct, hi_pct])
        if not hi > lo:
            hi = lo + 1.0
        out[k] = np.clip((a[k] - lo) / (hi - lo), 0.0, 1.0)
    out[:, ~ok] = 0.5
    return out, ok


def match_bands(
    a: np.ndarray, b: np.ndarray, names_a: Sequence[str] | None = None, names_b: Sequence[str] | None = None
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Bring two images to the same bands: equal counts are kept, else both become grey (with a note)."""
    notes = []
    if a.shape[0] != b.shape[0]:
        notes.append(f"the images have {a.shape[0]} and {b.shape[0]} bands: both compared in grey")
        return grey(a)[None], grey(b)[None], notes
    return a, b, notes


def _otsu(v: np.ndarray) -> float:
    from skimage.filters import threshold_otsu

    v = v[np.isfinite(v)]
    if v.size < 16 or np.ptp(v) <= 0:
        return float("inf")
    return float(threshold_otsu(v))


def vegetation_index(image: np.ndarray, band_names: Sequence[str] | None = None) -> np.ndarray | None:
    """NDVI when the image has a band named ``nir`` (and red: the band named ``red``, else the first),
    else the excess-green index (2g − r − b)/(r + g + b) of RGB; None for a grey image."""
    names = [str(n).lower() for n in (band_names or [])]
    a = np.asarray(image, np.float32)
    if "nir" in names and a.shape[0] >= 2:
        nir = a[names.index("nir")]
        red = a[names.index("red")] if "red" in names else a[0]
        return (nir - red) / np.maximum(nir + red, 1e-6)
    if a.shape[0] >= 3:
        r, g, b = a[0], a[1], a[2]
        return (2 * g - r - b) / np.maximum(r + g + b, 1e-6)
    return None


def vegetation_mask(
    image: np.ndarray, valid: np.ndarray, band_names: Sequence[str] | None = None, threshold: float | None = None
) -> np.ndarray | None:
    """Vegetation from NDVI or the excess-green index (:func:`vegetation_index`); None for grey.

    The threshold (default) is the image's own Otsu split of the index, but never below NDVI 0.2 /
    ExG 0.05 (an image without vegetation must not split its bare ground in two).
    """
    idx = vegetation_index(image, band_names)
    if idx is None:
        return None
    if threshold is None:
        names = [str(n).lower() for n in (band_names or [])]
        threshold = max(_otsu(idx[valid]), 0.2 if "nir" in names else 0.05)
    return (idx > threshold) & valid


def shadow_mask(
    image: np.ndarray, valid: np.ndarray, ratio: float = 0.5, min_px: int = 8, median: float | None = None
) -> np.ndarray:
    """Cast shadows: luminance below ``ratio`` × the image's median luminance (``median``: the whole
    image's, when this is a window of it), small specks removed."""
    from scipy import ndimage

    L = grey(image)
    if median is None:
        median = float(np.median(L[valid])) if valid.any() else 0.5
    m = (L < ratio * median) & valid
    m = ndimage.binary_opening(m, structure=np.ones((2, 2), bool))
    lab, n = ndimage.label(m)
    if n:
        sizes = np.bincount(lab.ravel())
        m = sizes[lab] >= min_px
        m[lab == 0] = False
    return m


# ---------------------------------------------------------------------------------------------
# dissimilarity
# ---------------------------------------------------------------------------------------------
def cell_valid(valid: np.ndarray, cell: int, min_valid: float) -> np.ndarray:
    from .features import cell_mean

    return cell_mean(valid.astype(np.float32), cell) >= min_valid


def spread_to_pixels(d_cells: np.ndarray, shape: tuple[int, int], cell: int, how: str = "bilinear") -> np.ndarray:
    """Cell values → pixels: bilinear between cell centres (edge values held outside), or nearest."""
    h, w = d_cells.shape
    H, W = shape
    if h == 0 or w == 0:
        return np.full(shape, np.nan, np.float32)
    if how == "nearest":
        r = np.minimum(np.arange(H) // cell, h - 1)
        c = np.minimum(np.arange(W) // cell, w - 1)
        return d_cells[r][:, c].astype(np.float32)
    fr = np.clip((np.arange(H) + 0.5) / cell - 0.5, 0, h - 1)
    fc = np.clip((np.arange(W) + 0.5) / cell - 0.5, 0, w - 1)
    r0 = np.floor(fr).astype(int)
    c0 = np.floor(fc).astype(int)
    r1 = np.minimum(r0 + 1, h - 1)
    c1 = np.minimum(c0 + 1, w - 1)
    tr = (fr - r0)[:, None]
    tc = (fc - c0)[None, :]
    d = np.where(np.isfinite(d_cells), d_cells, np.nan)
    # NaN-aware bilinear: weights of missing corners go to the others
    vals = [d[r0][:, c0], d[r0][:, c1], d[r1][:, c0], d[r1][:, c1]]
    wts = [(1 - tr) * (1 - tc), (1 - tr) * tc, tr * (1 - tc), tr * tc]
    num = np.zeros(shape, np.float64)
    den = np.zeros(shape, np.float64)
    for v, wt in zip(vals, wts):
        ok = np.isfinite(v)
        num += np.where(ok, v, 0) * wt
        den += ok * wt
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 1e-9, num / den, np.nan).astype(np.float32)


def superpixels(
    image: np.ndarray, method: str, gsd_m: float, segment_m: float, fz_scale: float = 100.0, fz_sigma: float = 0.8
) -> np.ndarray | None:
    """Superpixel labels (rows, cols) int of one image (None for "none")."""
    if method == "none":
        return None
    from skimage.segmentation import felzenszwalb, slic

    side_px = max(segment_m / max(gsd_m, 1e-9), 2.0)
    img = np.transpose(np.asarray(image, np.float32), (1, 2, 0))
    if img.shape[2] == 1:
        img = img[..., 0]
        ch = None
    else:
        img = img[..., :3]
        ch = -1
    if method == "felzenszwalb":
        return felzenszwalb(
            img, scale=fz_scale, sigma=fz_sigma, min_size=max(int(side_px * side_px / 4), 4), channel_axis=ch
        )
    n = max(int(img.shape[0] * img.shape[1] / (side_px * side_px)), 1)
    return slic(
        img,
        n_segments=n,
        compactness=0.1 if img.ndim == 2 else 10.0,
        start_label=0,
        channel_axis=ch,
        enforce_connectivity=True,
    )


def segment_mean(values: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Each pixel ← the mean of the finite values of its segment (NaN where a segment has none)."""
    lab = labels.ravel()
    v = values.ravel().astype(np.float64)
    ok = np.isfinite(v)
    n = lab.max() + 1
    s = np.bincount(lab[ok], weights=v[ok], minlength=n)
    c = np.bincount(lab[ok], minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = np.where(c > 0, s / np.maximum(c, 1), np.nan)
    return m[lab].reshape(values.shape).astype(np.float32)


def cell_distance(fa: np.ndarray, fb: np.ndarray) -> np.ndarray:
    """d_g = |x_g^A − x_g^B| per cell (eq. 4.1). A cell without signal has a zero descriptor: two such
    cells are alike (0), one against a textured cell is at distance 1."""
    return np.linalg.norm(fa - fb, axis=-1).astype(np.float32)


#: the last few feature and superpixel arrays computed, by content: a view screened against two others (the
#: cross-date pair and the no-change pair share one) is described and segmented once per window
_MEMO: OrderedDict = OrderedDict()
_MEMO_SIZE = 8


def _memo(kind: str, image: np.ndarray, extra, fn):
    """fn() for this image content and these settings, reused when the same window was seen recently (read-only)."""
    a = np.ascontiguousarray(image)
    key = (kind, a.shape, a.dtype.str, hashlib.blake2b(a.view(np.uint8).ravel(), digest_size=16).hexdigest(), extra)
    if key in _MEMO:
        _MEMO.move_to_end(key)
        return _MEMO[key]
    out = fn()
    if isinstance(out, np.ndarray):
        out.flags.writeable = False
    _MEMO[key] = out
    while len(_MEMO) > _MEMO_SIZE:
        _MEMO.popitem(last=False)
    return out


def screen_pair(
    image_a: np.ndarray,
    image_b: np.ndarray,
    *,
    gsd_m: float,
    params: ScreenParams = ScreenParams(),
    valid_a: np.ndarray | None = None,
    valid_b: np.ndarray | None = None,
    band_names_a: Sequence[str] | None = None,
    band_names_b: Sequence[str] | None = None,
    feature: GridFeature | None = None,
    normalised: bool = False,
    levels_a: dict | None = None,
    levels_b: dict | None = None,
) -> ScreenResult:
    """Screen two images of one grid (the same shape), eqs. 4.1–4.4.

    Parameters
    ----------
    image_a, image_b : (bands, rows, cols) any dtype (or (rows, cols)); NaN = not valid
    gsd_m : ground size of a pixel (m), scales the superpixels
    params : ScreenParams
    valid_a, valid_b : optional bool (rows, cols)
    band_names_a, band_names_b : band names (a ``nir`` band enables NDVI)
    feature : a built extractor (default ``params.feature.build()``; pass one to reuse a CNN)
    normalised : the images are already stretched to 0–1 (skip :func:`normalise_image`)
    levels_a, levels_b : whole-image levels when the arrays are windows of larger images:
        ``veg_threshold`` (index), ``shadow_median`` (luminance); default: measured on the arrays

    Returns
    -------
    ScreenResult
    """
    a = np.asarray(image_a)
    b = np.asarray(image_b)
    if a.ndim == 2:
        a = a[None]
    if b.ndim == 2:
        b = b[None]
    if a.shape[-2:] != b.shape[-2:]:
        raise GridError(
            f"the two images must be on one grid: shapes {a.shape[-2:]} and {b.shape[-2:]}; resample "
            "one onto the other's grid first (geocd screen does this for files)"
        )
    notes: list[str] = []
    if normalised:
        na = a.astype(np.float32)
        va = np.ones(a.shape[-2:], bool) if valid_a is None else np.asarray(valid_a, bool)
        nb = b.astype(np.float32)
        vb = np.ones(b.shape[-2:], bool) if valid_b is None else np.asarray(valid_b, bool)
    else:
        na, va = normalise_image(a, valid_a)
        nb, vb = normalise_image(b, valid_b)
    fa_img, fb_img, n2 = match_bands(na, nb)
    notes += n2
    feat = feature or params.feature.build()
    cell = int(feat.cell_px)
    H, W = a.shape[-2:]
    if H < cell or W < cell:
        raise GridError(f"the images ({H} × {W} px) are smaller than one grid cell ({cell} px)")
    if feature is None and params.feature.kind != "cnn":  # weight-free features: a spec describes a window one way
        spec = repr(params.feature)
        xa = _memo("feature", fa_img, spec, lambda: feat.extract(fa_img))
        xb = _memo("feature", fb_img, spec, lambda: feat.extract(fb_img))
    else:
        xa = feat.extract(fa_img)
        xb = feat.extract(fb_img)
    valid = va & vb
    d_cells = cell_distance(xa, xb)
    cv = cell_valid(valid, cell, params.min_valid)
    d_cells = np.where(cv, d_cells, np.nan).astype(np.float32)
    unrelated = unrelated_distance(xa, xb, cv)
    d_pix = spread_to_pixels(d_cells, (H, W), cell, params.spread)
    d_pix = np.where(valid, d_pix, np.nan).astype(np.float32)
    if params.superpixels != "none":
        sp = (params.superpixels, float(gsd_m), params.segment_m, params.fz_scale, params.fz_sigma)
        la = _memo("superpixels", na, sp, lambda: superpixels(na, *sp))
        lb = _memo("superpixels", nb, sp, lambda: superpixels(nb, *sp))
        sa = segment_mean(d_pix, la)
        sb = segment_mean(d_pix, lb)
        with np.errstate(invalid="ignore"):
            d = np.fmax(sa, sb)
        d = np.where(valid, d, np.nan).astype(np.float32)
    else:
        d = d_pix.copy()
    excl = np.zeros((H, W), np.uint8)
    if params.vegetation != "off":
        ga = vegetation_mask(na, va, band_names_a, (levels_a or {}).get("veg_threshold"))
        gb = vegetation_mask(nb, vb, band_names_b, (levels_b or {}).get("veg_threshold"))
        if ga is None or gb is None:
            notes.append("vegetation not excluded: it needs colour (RGB) or a nir band in both images")
        else:
            m = (ga & gb) if params.vegetation == "both" else (ga | gb)
            excl |= (m * EXCL_VEGETATION).astype(np.uint8)
    if params.shadow != "off":
        sa_ = shadow_mask(na, va, median=(levels_a or {}).get("shadow_median"))
        sb_ = shadow_mask(nb, vb, median=(levels_b or {}).get("shadow_median"))
        m = (sa_ & sb_) if params.shadow == "both" else (sa_ | sb_)
        excl |= (m * EXCL_SHADOW).astype(np.uint8)
    d = np.where((excl > 0) & np.isfinite(d), 0.0, d).astype(np.float32)
    return ScreenResult(d, d_pix, d_cells, excl, valid, cell, unrelated, notes)


def shift_image(image: np.ndarray, shift_px: float, angle_deg: float = 30.0) -> np.ndarray:
    """Shift an image by ``shift_px`` pixels towards ``angle_deg`` (bilinear; edges repeated): misregistration."""
    from scipy.ndimage import shift

    a = np.asarray(image, np.float32)
    dy = shift_px * math.sin(math.radians(angle_deg))
    dx = shift_px * math.cos(math.radians(angle_deg))
    if a.ndim == 2:
        return shift(a, (dy, dx), order=1, mode="nearest")
    return np.stack([shift(x, (dy, dx), order=1, mode="nearest") for x in a])
