"""Parameters of the object-space stereo matcher."""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import ConfigError
from ..params import ParamsMixin
from .scores import SCORES


@dataclass(frozen=True)
class StereoParams(ParamsMixin):
    """Everything that tunes :func:`geocd.stereo.match_pair`.

    Attributes
    ----------
    window : int
        Matching window side in grid cells (odd).
    max_step_px : float
        Height step: one step moves the projection by at most this many pixels in
        the more sensitive image (issue 4: 0.5).
    height_range_m : (float, float), optional
        Ellipsoidal height search range; overrides the cameras' range (not a DEM).
    dem_margin_m : float
        With a prior DEM, search ``[min − margin, max + margin]`` of the DEM over a
        ``dem_window``-cell neighbourhood (buildings and trees are not in a bare DEM).
    dem_window : int
        Neighbourhood (cells) of the DEM min/max above.
    max_heights : int
        When a cell would need more height steps than this at full resolution, the
        range is first narrowed coarse-to-fine (grids 2×, 4×, … coarser).
    max_coarse_heights : int
        Hard cap on the height planes per cell of the coarsest level; a pair that would need
        more (a huge range for a small AOI) stops with a ConfigError naming the fix instead of
        running for hours. 4096 = 32 × ``max_heights``: the coarsest level of a 1000 × 1000-cell
        AOI then costs at most what 32 full-resolution levels do.
    refine_margin_steps : float
        Margin around the coarser level's heights, in that level's height steps.
    min_valid_fraction : float
        A window needs this fraction of cells valid in both images.
    noise_sigma : float, optional
        Image noise σ_n on the normalized 8-bit scale; None = estimated per image.
    min_ncc : float
        Matches with a lower NCC are invalid.
    uniqueness_ratio : float
        Invalid when ``(1 − NCC_best) > uniqueness_ratio · (1 − NCC_second)`` for the best
        other local minimum more than ``uniqueness_exclusion_px`` of disparity away.
    uniqueness_exclusion_px : float
    texture_min_snr : float
        Invalid when either window's standard deviation is below ``texture_min_snr · σ_n``.
    occlusion_check : bool
        Z-buffer test in each image: cells hidden behind a higher cell are invalid.
    occlusion_tol_px : float
        Height tolerance of that test, in pixels of image motion.
    isolation_min_cells : int, optional
        Neighbour agreement: a valid height whose surface patch (4-neighbours joined when their heights differ
        by less than ``isolation_tol_px`` of disparity) holds fewer cells than this is invalid (flag
        ``not_unique``: no surface around it supports it; :func:`geocd.stereo.match.isolated_matches`).
        None (default) = one matching window (``window²`` cells), the smallest surface a window matcher
        resolves; 1 = off. Measured on the Réunion pair against s2p's DSM (``bench/eval_stereo_validity.py``).
    isolation_tol_px : float
        Height difference between neighbours of one surface, in pixels of disparity (1 px = ``1 / g`` metres).
    min_base_height : float
        Cells whose pair geometry has a base/height ratio (≈ g / image sampling) below
        this are invalid; a pair below it everywhere is skipped with a warning.
    score : str
        What ``PairDEM.score`` holds (lower = better): "mdl" (bits/pixel), "ncc"
        (1 − NCC) or "ssd". All three are written to the products anyway.
    score_subwindow : int
        The MDL score of a match is the worst (largest) MDL score of the
        ``score_subwindow``-cell sub-windows tiling its matching window, at the matched
        height (:func:`geocd.stereo.subwindow_mdl`): a window that only part of the
        surface explains (one straddling a height step) does not pass for a good
        match. ``≥ window`` scores the matching window as a whole.
    surface_median : int, optional
        Odd window side (cells) of a median over the *valid* heights, applied after the
        validity tests (validity, scores and flags unchanged). None (default) = the matching
        window: a height already stands for its whole window, so a median over that window
        removes no detail the match resolved, only the scatter of neighbouring matches
        (measured against exact truth on sample_aoi and against s2p on Réunion and
        Marseille, docs/stereo.md). 1 = off.
    fill_holes : bool
        Interpolate heights into holes narrower than the matching window (no cell more than
        a window radius from a valid cell; not touching the grid's border): ``z`` holds them,
        ``valid`` stays False and the flag ``filled`` is set (products.FLAGS).
    norm_block_px : int
        Region size of the local photometric normalization (image pixels).
    tile_size : int
        Tile side (grid cells); memory per tile ≈ 0.3 KB per cell.
    pointing_correction : bool
        Estimate and remove the pair's relative pointing error across the epipolar
        direction (:mod:`geocd.stereo.pointing`) from a coarse match before the fine one.
    max_pointing_px : float
        Largest relative pointing error searched at the coarse level (pixels).
    min_pointing_px : float
        A relative pointing correction smaller than this (pixels, coarse + fine) is not
        applied: on sample_aoi's exact cameras the estimator returns up to 0.22 px of bias
        (0.46 px when the patch estimate rests on 8 patches).
    min_pointing_patches : int
        The fine (patch) estimate is used only when at least this many 48-cell patches
        agree on it (the coarse level's estimate alone stands otherwise).
    """

    window: int = 7
    max_step_px: float = 0.5
    height_range_m: tuple[float, float] | None = None
    dem_margin_m: float = 30.0
    dem_window: int = 5
    max_heights: int = 128
    max_coarse_heights: int = 4096
    refine_margin_steps: float = 3.0
    min_valid_fraction: float = 0.75
    noise_sigma: float | None = None
    min_ncc: float = 0.3
    uniqueness_ratio: float = 0.95
    uniqueness_exclusion_px: float = 1.5
    texture_min_snr: float = 1.0
    occlusion_check: bool = True
    occlusion_tol_px: float = 1.0
    isolation_min_cells: int | None = None
    isolation_tol_px: float = 1.0
    min_base_height: float = 0.05
    score: str = "mdl"
    score_subwindow: int = 3
    surface_median: int | None = None
    fill_holes: bool = True
    norm_block_px: int = 256
    tile_size: int = 256
    pointing_correction: bool = True
    max_pointing_px: float = 6.0
    min_pointing_px: float = 0.25
    min_pointing_patches: int = 16

    def __post_init__(self) -> None:
        if self.window < 3 or self.window % 2 == 0:
            raise ConfigError(f"stereo window must be an odd number ≥ 3 of cells, got {self.window}")
        if not (0.0 < self.max_step_px <= 2.0):
            raise ConfigError(f"max_step_px must be in (0, 2], got {self.max_step_px}")
        if self.height_range_m is not None:
            lo, hi = (float(v) for v in self.height_range_m)
            if not hi > lo:
                raise ConfigError(
                    f"height range {self.height_range_m} is empty; give (min, max) with max > min (metres)"
                )
            object.__setattr__(self, "height_range_m", (lo, hi))
        if self.dem_margin_m < 0:
            raise ConfigError(f"dem_margin_m must be ≥ 0, got {self.dem_margin_m}")
        if self.max_heights < 8:
            raise ConfigError(f"max_heights must be ≥ 8, got {self.max_heights}")
        if self.max_coarse_heights < self.max_heights:
            raise ConfigError(
                f"max_coarse_heights must be ≥ max_heights ({self.max_heights}), got {self.max_coarse_heights}"
            )
        if not (0.0 < self.min_valid_fraction <= 1.0):
            raise ConfigError(f"min_valid_fraction must be in (0, 1], got {self.min_valid_fraction}")
        if self.score not in SCORES:
            raise ConfigError(f"score must be one of {SCORES}, got {self.score!r}")
        if not self.min_pointing_px >= 0:
            raise ConfigError(f"min_pointing_px must be ≥ 0 pixels, got {self.min_pointing_px}")
        if self.min_pointing_patches < 1:
            raise ConfigError(f"min_pointing_patches must be ≥ 1, got {self.min_pointing_patches}")
        if self.score_subwindow < 3 or self.score_subwindow % 2 == 0:
            raise ConfigError(f"score_subwindow must be an odd number ≥ 3 of cells, got {self.score_subwindow}")
        if self.surface_median is not None and (self.surface_median < 1 or self.surface_median % 2 == 0):
            raise ConfigError(
                f"surface_median must be an odd number ≥ 1 of cells (1 = off; None = the window), "
                f"got {self.surface_median}"
            )
        if self.isolation_min_cells is not None and self.isolation_min_cells < 1:
            raise ConfigError(
                f"isolation_min_cells must be ≥ 1 cells (1 = off; None = one window), got {self.isolation_min_cells}"
            )
        if not self.isolation_tol_px > 0:
            raise ConfigError(f"isolation_tol_px must be > 0 pixels of disparity, got {self.isolation_tol_px}")
        if self.tile_size < 32:
            raise ConfigError(f"tile_size must be ≥ 32 cells, got {self.tile_size}")
        if self.noise_sigma is not None and not self.noise_sigma > 0:
            raise ConfigError(f"noise_sigma must be positive, got {self.noise_sigma}")

    _kind = "stereo"  # names the parameter set in ConfigError messages

    @property
    def radius(self) -> int:
        return self.window // 2

    @property
    def isolation_cells(self) -> int:
        """Smallest valid surface patch (cells; 1 = the neighbour-agreement test is off)."""
        return self.window**2 if self.isolation_min_cells is None else int(self.isolation_min_cells)

    @property
    def median_size(self) -> int:
        """The surface median's window side (cells; 1 = none)."""
        return self.window if self.surface_median is None else int(self.surface_median)


def isolation_cells(params: dict) -> int:
    """The neighbour-agreement minimum (cells; 1 = off) a pair-DEM's recorded stereo parameters say it was
    matched with: 1 when the key is absent (made before the test existed), one window when it is None."""
    if "isolation_min_cells" not in params:
        return 1
    n = params["isolation_min_cells"]
    return int(params.get("window", StereoParams.window)) ** 2 if n is None else int(n)


def surface_median_cells(params: dict) -> int:
    """The surface median (cells) a pair-DEM's recorded stereo parameters say it was matched with: 1 when the
    key is absent (made before the median existed), the matching window when it is None (the default)."""
    sm = params.get("surface_median", 1)
    return int(params.get("window", StereoParams.window)) if sm is None else int(sm)


#: the change test reads each cell's own match: its self-consistency model and region null describe the error
#: of one match, and a median over the matching window mixes neighbours' errors (measured on sample_aoi:
#: region-test precision 0.79 -> 0.72 with it), so a change run's stereo leaves it out unless a config sets it.
#: The neighbour-agreement test likewise makes a cell's validity depend on its neighbours' heights; measured
#: with it: sample_aoi region-test precision 0.79 -> 0.70, per-cell 0.47 -> 0.40; Kahramanmaraş 12 of the 14
#: new buildings marked by eye found instead of 14 (one left unobserved), 2 of 79 unchanged ones flagged
#: instead of 0. The change test's own statistics stand in for it there.
RUN_STEREO_DEFAULTS = {"surface_median": 1, "isolation_min_cells": 1}


def change_stereo_params(d: dict | None = None) -> "StereoParams":
    """The stereo parameters of a change run (``geocd run``, ``geocd mpp``): :class:`StereoParams` with
    :data:`RUN_STEREO_DEFAULTS`, then ``d`` (a config's ``stereo`` section) over them."""
    return StereoParams.from_dict({**RUN_STEREO_DEFAULTS, **(d or {})})
