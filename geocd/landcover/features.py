"""Per-pixel features for land-cover classification (arrays in, arrays out).

The features follow Sakurada's thesis (ch. 6.2.1): colour, the mean and variance
of the grey level in a 5 × 5 patch, texture, and — where a DSM exists — the
height above ground. Colour is CIE Lab (scikit-image ``rgb2lab``) of the first
three bands (the lightness alone for a single-band image; further bands, e.g.
near-infrared, are added as they are). Texture is scikit-image's
``multiscale_basic_features`` of the grey level: Gaussian-smoothed intensity,
gradient magnitude and the two Hessian eigenvalues at each scale.

Radiometry is normalised per image and band by robust percentiles (1 % → 0,
99 % → 1 over the valid pixels), so a model trained on one view applies to
another with a different gain, offset or haze.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, EmptyDataError
from ..params import ParamsMixin


@dataclass(frozen=True)
class FeatureSpec(ParamsMixin):
    """Which per-pixel features to compute (stored with a trained model and checked on load).

    Attributes
    ----------
    colour : bool
        CIE Lab of bands 1–3 (L only for a single-band image) and any further bands as they are.
    patch_px : int
        Side of the square patch of the grey mean / variance features (odd; thesis: 5).
    texture_sigmas_px : tuple of float
        Scales (pixels) of scikit-image's multiscale intensity / edge / Hessian texture features;
        empty = none.
    height_above_ground : bool
        Add the height above ground (m) of the surface a pixel sees (needs a DSM and a DEM).
    percentiles : (low, high)
        Per-band radiometric normalisation percentiles.
    """

    _kind = "landcover feature"

    colour: bool = True
    patch_px: int = 5
    texture_sigmas_px: tuple = (1.0, 2.0, 4.0)
    height_above_ground: bool = False
    percentiles: tuple = (1.0, 99.0)

    def __post_init__(self) -> None:
        if self.patch_px < 1 or self.patch_px % 2 == 0:
            raise ConfigError(f"patch_px must be a positive odd number, got {self.patch_px}")
        if any(not (s > 0) for s in self.texture_sigmas_px):
            raise ConfigError(f"texture scales must be positive pixels, got {self.texture_sigmas_px}")
        lo, hi = self.percentiles
        if not (0 <= lo < hi <= 100):
            raise ConfigError(f"percentiles must satisfy 0 ≤ low < high ≤ 100, got {self.percentiles}")

    def names(self, n_bands: int) -> list[str]:
        """Feature names (in order) for an image of ``n_bands`` bands."""
        out: list[str] = []
        if self.colour:
            out += ["L", "a", "b"] if n_bands >= 3 else ["L"]
            first_extra = 3 if n_bands >= 3 else 1
            out += [f"band{k + 1}" for k in range(first_extra, n_bands)]
        out += [f"grey_mean_{self.patch_px}", f"grey_var_{self.patch_px}"]
        for s in self.texture_sigmas_px:
            out += [f"intensity_s{s:g}", f"edges_s{s:g}", f"hessian1_s{s:g}", f"hessian2_s{s:g}"]
        if self.height_above_ground:
            out.append("height_above_ground_m")
        return out


def normalize_bands(data: np.ndarray, valid: np.ndarray, percentiles: tuple = (1.0, 99.0)) -> np.ndarray:
    """Scale each band so its ``percentiles`` over the valid pixels map to 0 and 1 (float32, clipped to [-0.5, 1.5]).

    Parameters
    ----------
    data : (bands, rows, cols) any numeric dtype
    valid : bool (rows, cols)
    """
    a = np.asarray(data, np.float32)
    if a.ndim == 2:
        a = a[None]
    ok = np.asarray(valid, bool)
    if not ok.any():
        raise EmptyDataError("the image has no valid pixel")
    out = np.empty_like(a)
    for k in range(a.shape[0]):
        v = a[k][ok]
        lo, hi = np.percentile(v, percentiles)
        if not hi > lo:
            hi = lo + 1.0
        out[k] = np.clip((a[k] - lo) / (hi - lo), -0.5, 1.5)
    out[:, ~ok] = 0.0
    return out


def _box_mean(a: np.ndarray, ok: np.ndarray, size: int) -> np.ndarray:
    from scipy import ndimage

    num = ndimage.uniform_filter(np.where(ok, a, 0.0).astype(np.float64), size, mode="nearest")
    den = ndimage.uniform_filter(ok.astype(np.float64), size, mode="nearest")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.maximum(den, 1e-12), 0.0)


def pixel_features(
    data: np.ndarray,
    valid: np.ndarray,
    spec: FeatureSpec = FeatureSpec(),
    height_above_ground_m: np.ndarray | None = None,
) -> np.ndarray:
    """Feature stack of an image.

    Parameters
    ----------
    data : (bands, rows, cols) or (rows, cols), any numeric dtype (raw pixel values)
    valid : bool (rows, cols); invalid pixels get features 0 (the caller masks them)
    spec : FeatureSpec
    height_above_ground_m : float (rows, cols), optional
        Required when ``spec.height_above_ground``; NaN (unknown) becomes 0.

    Returns
    -------
    float32 (n_features, rows, cols), in the order of ``spec.names(bands)``.
    """
    from skimage.color import rgb2lab
    from skimage.feature import multiscale_basic_features

    a = np.asarray(data)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3:
        raise ConfigError(f"image must be (bands, rows, cols), got shape {a.shape}")
    ok = np.asarray(valid, bool)
    if ok.shape != a.shape[1:]:
        raise ConfigError(f"valid mask shape {ok.shape} does not match the image {a.shape[1:]}")
    x = normalize_bands(a, ok, spec.percentiles)
    nb = x.shape[0]
    grey = x[:3].mean(axis=0) if nb >= 3 else x[0]
    feats: list[np.ndarray] = []
    if spec.colour:
        if nb >= 3:
            lab = rgb2lab(np.clip(np.moveaxis(x[:3], 0, -1), 0.0, 1.0))
            feats += [lab[..., 0] / 100.0, lab[..., 1] / 100.0, lab[..., 2] / 100.0]
            feats += list(x[3:])
        else:
            feats.append(grey)
            feats += list(x[1:])
    m = _box_mean(grey, ok, spec.patch_px)
    m2 = _box_mean(grey * grey, ok, spec.patch_px)
    feats += [m, np.maximum(m2 - m * m, 0.0)]
    for s in spec.texture_sigmas_px:
        f = multiscale_basic_features(
            grey.astype(np.float64),
            intensity=True,
            edges=True,
            texture=True,
            sigma_min=float(s),
            sigma_max=float(s),
            num_sigma=1,
        )
        feats += [f[..., k] for k in range(f.shape[-1])]
    if spec.height_above_ground:
        if height_above_ground_m is None:
            raise ConfigError(
                "this feature set uses the height above ground: give a DSM and a DEM (or a model "
                "trained without --height-above-ground)"
            )
        h = np.asarray(height_above_ground_m, np.float32)
        if h.shape != ok.shape:
            raise ConfigError(f"height-above-ground shape {h.shape} does not match the image {ok.shape}")
        feats.append(np.where(np.isfinite(h), h, 0.0))
    out = np.stack(feats).astype(np.float32)
    out[:, ~ok] = 0.0
    return out
