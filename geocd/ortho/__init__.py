"""Orthoimages: any image (RPC or frame camera) onto the AOI grid with a DSM, true ortho.

* :func:`orthorectify` — arrays in, arrays out: an image-space array (any bands,
  any dtype, e.g. a class-probability map), a camera, a grid and a DSM array →
  values, observed mask, per-cell status and view weights.
* :func:`view_geometry`, :func:`fill_dsm_holes`, :func:`occlusion_margin_cells`.
* :mod:`geocd.ortho.pipeline` — files: image windows, DSMs from geocd stereo or
  given, COG products (``geocd ortho``).
"""

from .core import (
    NO_HEIGHT,
    OCCLUDED,
    OUTSIDE_IMAGE,
    SEEN,
    SEEN_FILLED_HEIGHT,
    STATUS_LABELS,
    STATUS_NAMES,
    OrthoParams,
    OrthoResult,
    ViewGeometry,
    dsm_noise_m,
    fill_dsm_holes,
    occlusion_margin_cells,
    orthorectify,
    view_geometry,
)

__all__ = [
    "NO_HEIGHT",
    "OCCLUDED",
    "OUTSIDE_IMAGE",
    "SEEN",
    "SEEN_FILLED_HEIGHT",
    "STATUS_LABELS",
    "STATUS_NAMES",
    "OrthoParams",
    "OrthoResult",
    "ViewGeometry",
    "dsm_noise_m",
    "fill_dsm_holes",
    "occlusion_margin_cells",
    "orthorectify",
    "view_geometry",
]
