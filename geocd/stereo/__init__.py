"""Object-space stereo: dense pair-DEMs with MDL scores and disparity normalization (issue 4).

Public API
----------
* :func:`match_pair` — one image pair → :class:`PairDEM` (arrays on an AOI grid).
* :func:`prepare_chip` / :class:`ImageChip` — normalized images to match.
* :class:`StereoParams` — every tunable, frozen.
* :class:`PlaneSweep`, :class:`HeightSearch`, :class:`SweepSlice`, :func:`window_mean` —
  the reusable height-sweep warping machinery (plug any per-height cost in).
* :func:`write_pair_dem` / :func:`read_pair_dem` — the GeoTIFF product.
* :func:`run_stereo` — every pair of a manifest's epochs, products on disk
  (``geocd stereo`` CLI); :func:`read_chip` reads an image window for a grid.
* scores: :func:`subwindow_mdl` (the MDL score of a match: worst sub-window), :func:`mdl_from_stats`,
  :func:`ncc_from_stats`, :func:`ssd_from_stats`.
"""

from .match import (
    StereoGeometryWarning,
    height_bounds,
    local_projection,
    match_pair,
    occlusion_mask,
    pair_geometry,
    subwindow_mdl,
    sweep_ncc,
)
from .params import StereoParams
from .products import BANDS, FLAGS, PairDEM, read_pair_dem, write_pair_dem
from .scores import mdl_from_stats, mdl_score_ref, ncc_from_stats, ssd_from_stats
from .sweep import HeightSearch, ImageChip, PlaneSweep, SweepSlice, Tile, iter_tiles, prepare_chip, window_mean


def __getattr__(name):  # lazy: these read and write files
    if name in ("run_stereo", "pair_path"):
        from . import pipeline

        return getattr(pipeline, name)
    if name in ("read_chip", "default_aoi_grid", "load_epoch_images"):
        from . import scene

        return getattr(scene, name)
    raise AttributeError(name)


__all__ = [
    "BANDS",
    "FLAGS",
    "HeightSearch",
    "ImageChip",
    "PairDEM",
    "PlaneSweep",
    "StereoGeometryWarning",
    "StereoParams",
    "SweepSlice",
    "Tile",
    "height_bounds",
    "iter_tiles",
    "match_pair",
    "mdl_from_stats",
    "mdl_score_ref",
    "ncc_from_stats",
    "occlusion_mask",
    "pair_geometry",
    "prepare_chip",
    "read_pair_dem",
    "ssd_from_stats",
    "subwindow_mdl",
    "local_projection",
    "sweep_ncc",
    "window_mean",
    "write_pair_dem",
    "run_stereo",
    "read_chip",
    "default_aoi_grid",
    "pair_path",
    "load_epoch_images",
]
