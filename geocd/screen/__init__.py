"""Fast 2-D screening: grid-feature change with superpixels (Sakurada's thesis, ch. 4).

The first pass over a whole city: two images of one grid (orthoimages, or raw views
projected on the terrain) compared cell by cell with normalised grid features, refined
with superpixels, with vegetation and cast shadows seen in both dates set aside. It is
fast (seconds per km²), tolerant of a few pixels of misregistration, and tells the
slower 3-D methods where to look (``geocd run --screen``).

* :mod:`geocd.screen.features` — grid features behind one interface (CNN pooling layers from
  weights the user names, a seeded random-filter bank, dense DAISY, grey patches);
* :mod:`geocd.screen.cnn` — VGG- and ResNet-style backbones, numpy and PyTorch forward passes;
* :func:`screen_pair` — arrays in, arrays out (eqs. 4.1–4.4);
* :mod:`geocd.screen.threshold` — thresholds from a no-change pair or labelled pairs;
* :mod:`geocd.screen.pipeline` — files: two rasters or a manifest's views, per AOI window
  through :mod:`geocd.tiling`, products in the shared change layers (``geocd screen``).
"""

from .core import (
    EXCL_SHADOW,
    EXCL_VEGETATION,
    ScreenParams,
    ScreenResult,
    normalise_image,
    screen_pair,
    segment_mean,
    shadow_mask,
    shift_image,
    spread_to_pixels,
    superpixels,
    vegetation_mask,
)
from .features import FEATURES, CNNFeature, DaisyFeature, FeatureSpec, GridFeature, PatchFeature, RandomBankFeature
from .threshold import NullDistribution, f1_scores, threshold_best_f1, threshold_from_nochange

__all__ = [
    "CNNFeature",
    "DaisyFeature",
    "EXCL_SHADOW",
    "EXCL_VEGETATION",
    "FEATURES",
    "FeatureSpec",
    "GridFeature",
    "NullDistribution",
    "PatchFeature",
    "RandomBankFeature",
    "ScreenParams",
    "ScreenResult",
    "f1_scores",
    "normalise_image",
    "screen_pair",
    "segment_mean",
    "shadow_mask",
    "shift_image",
    "spread_to_pixels",
    "superpixels",
    "threshold_best_f1",
    "threshold_from_nochange",
    "vegetation_mask",
]
