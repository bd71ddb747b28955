"""Parameters of the probabilistic structure-change detector (Sakurada's thesis, ch. 5)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from ..errors import ConfigError
from ..params import ParamsMixin

PAIR_MODES = ("star", "consecutive", "all")
BAND_MODES = ("all", "gray")


@dataclass(frozen=True)
class ProbChangeParams(ParamsMixin):
    """Everything that tunes :func:`geocd.probchange.detect_keyframe` and :func:`~geocd.probchange.detect_objectspace`.

    Attributes
    ----------
    n_bins : int
        Number of depth hypotheses along each ray (thesis: n = 128). Key-frame
        rays: bins uniform in disparity (image motion in the key frame's epoch
        views) — uniform inverse depth for frame cameras, uniform height for RPC
        views. Object space: bins uniform in height.
    window : int
        Patch side in pixels/cells (odd; thesis: 5 × 5).
    min_valid_fraction : float
        A patch dissimilarity needs this fraction of the window valid in both images.
    prior_change : float
        Prior p(c = 1) (thesis: 0.5), in (0, 1).
    sigma : float, optional
        σ of the half-Laplace density of correctly matched patch dissimilarities
        of the depth epoch (normalized 0–255 scale). None: estimated from the
        data as in §5.3.5 (half-Laplace fitted to the histogram of min_d s_d).
    sigma_prime : float, optional
        σ' of the other epoch; None: estimated the same way from its pairs.
    uniform_range : float, optional
        Width S of the uniform density p(s' | δ' = 0) = 1/S. None: the
        ``uniform_quantile`` of the sampled dissimilarities over all hypotheses.
    uniform_quantile : float
        See ``uniform_range``.
    sigma_fit_quantile : float
        The half-Laplace is fitted (maximum likelihood: the mean) to the values
        of min_d s_d below this quantile, so occlusions and specular spots in the
        tail do not inflate σ.
    sigma_sample_px : int
        At most this many reference pixels/cells (whole tiles spread over the
        area) are swept to estimate σ, σ' and S before the main sweep.
    symmetric : bool
        Also swap the epochs (depth density from the other epoch, observations
        from the first) and add both log-likelihood ratios (independent-observation
        approximation, like the pairs).
    no_depth_prior : float
        π∅, prior probability that no hypothesis of a ray is the surface in the
        depth epoch's images (the pixel is occluded in one of them, a depth edge
        cuts its patch, the surface is out of range). Its posterior is
        ``p(∅) ∝ π∅`` against ``p(d) ∝ (1 − π∅)/n · Π_pairs (S/σ) e^{−s_d/σ}``, so a ray
        whose best match is no better than chance keeps its depth density small
        and gives little evidence either way. 0 = the thesis's p(d) (sums to 1).
    visibility : bool
        Occlusion test: a first pass keeps each epoch's most probable hypothesis;
        pairs with a view in which the depth epoch's most probable surface point
        is hidden (height z-buffer) are not used as observations of that pixel.
        False = the thesis (no occlusion handling).
    visibility_tol_m : float
        A point is hidden when a higher point lands on its view pixel more than this above it.
    outlier_fraction : float
        ε in p(s' | δ' = 1) = (1 − ε) · half-Laplace + ε · uniform: a correctly
        placed hypothesis may still be occluded in one image of a pair. 0 = the
        thesis's model exactly.
    pairs : {"star", "consecutive", "all"}
        Pairs within an epoch: the reference (key frame / first image) with each
        other image, consecutive images, or all combinations. In the key-frame
        variant the key frame's epoch always uses "star" (s_d compares key-frame
        patches, eq. 5.1).
    bands : {"all", "gray"}
        Dissimilarity averaged over bands (eq. 5.1, when every image of an epoch
        has the same band count) or on gray levels.
    height_range_m : (float, float), optional
        Ellipsoidal height range of the hypotheses; overrides the prior DEM and the cameras.
    height_below_m, height_above_m : float
        With a prior (bare-earth) DEM: hypotheses from ``DEM − below`` to
        ``DEM + above`` (the DEM has no buildings or trees).
    dem_window : int
        Object space: the DEM's min/max over this many cells around each cell.
    norm_block_px : int
        Region size of the photometric normalization of each image (11-bit, RGB →
        0–255); the default is larger than any chip: one gain and offset per image,
        which the within-epoch alignment below can then undo exactly.
    align_radiometry : bool
        Within each epoch, fit every view's gray levels to the first view's (gain
        and offset per band, robust) at ground points on the prior DEM (or the
        middle of the height range), so eq. 5.1's absolute differences measure
        geometry, not haze and sensor gain.
    tile_size : int
        Tile side in pixels/cells; memory per tile ≈ 4 B × n_bins × pairs × tile².
    lattice_px : int
        Key-frame variant: hypotheses are projected exactly on a lattice of this
        spacing and interpolated bilinearly in between (refined automatically
        until the interpolation error is below ``interp_tol_px``).
    interp_tol_px : float
    threshold : float
        Binary change where p(c = 1 | …) > threshold (thesis: 0.5).
    min_region_cells : int
        Smallest changed region written as a polygon.
    """

    n_bins: int = 128
    window: int = 5
    min_valid_fraction: float = 0.6
    prior_change: float = 0.5
    sigma: float | None = None
    sigma_prime: float | None = None
    uniform_range: float | None = None
    uniform_quantile: float = 0.99
    sigma_fit_quantile: float = 0.95
    sigma_sample_px: int = 200_000
    symmetric: bool = False
    no_depth_prior: float = 0.0
    visibility: bool = False
    visibility_tol_m: float = 1.0
    outlier_fraction: float = 0.0
    pairs: str = "star"
    bands: str = "all"
    height_range_m: tuple[float, float] | None = None
    height_below_m: float = 5.0
    height_above_m: float = 40.0
    dem_window: int = 5
    norm_block_px: int = 1 << 16
    align_radiometry: bool = True
    tile_size: int = 128
    lattice_px: int = 8
    interp_tol_px: float = 0.05
    threshold: float = 0.5
    min_region_cells: int = 4

    def __post_init__(self) -> None:
        if not 2 <= self.n_bins <= 4096:
            raise ConfigError(f"n_bins must be in [2, 4096], got {self.n_bins}")
        if self.window < 1 or self.window % 2 == 0:
            raise ConfigError(f"window must be an odd number of pixels ≥ 1 (thesis: 5), got {self.window}")
        if not 0.0 < self.min_valid_fraction <= 1.0:
            raise ConfigError(f"min_valid_fraction must be in (0, 1], got {self.min_valid_fraction}")
        if not 0.0 < self.prior_change < 1.0:
            raise ConfigError(f"prior_change p(c=1) must be in (0, 1), got {self.prior_change}")
        for name in ("sigma", "sigma_prime", "uniform_range"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise ConfigError(f"{name} must be a positive number (0–255 scale) or None to estimate it, got {v}")
        for name in ("uniform_quantile", "sigma_fit_quantile"):
            v = getattr(self, name)
            if not 0.5 <= v <= 1.0:
                raise ConfigError(f"{name} must be in [0.5, 1], got {v}")
        if self.sigma_sample_px < 1000:
            raise ConfigError(f"sigma_sample_px must be ≥ 1000, got {self.sigma_sample_px}")
        if not 0.0 <= self.no_depth_prior < 1.0:
            raise ConfigError(f"no_depth_prior must be in [0, 1), got {self.no_depth_prior}")
        if not self.visibility_tol_m > 0:
            raise ConfigError(f"visibility_tol_m must be positive, got {self.visibility_tol_m}")
        if not 0.0 <= self.outlier_fraction < 1.0:
            raise ConfigError(f"outlier_fraction must be in [0, 1), got {self.outlier_fraction}")
        if self.pairs not in PAIR_MODES:
            raise ConfigError(f"pairs must be one of {PAIR_MODES}, got {self.pairs!r}")
        if self.bands not in BAND_MODES:
            raise ConfigError(f"bands must be one of {BAND_MODES}, got {self.bands!r}")
        if self.height_range_m is not None:
            lo, hi = (float(v) for v in self.height_range_m)
            if not hi > lo:
                raise ConfigError(
                    f"height range {self.height_range_m} is empty; give (min, max) with max > min (metres)"
                )
            object.__setattr__(self, "height_range_m", (lo, hi))
        if self.height_below_m < 0 or self.height_above_m < 0 or self.height_below_m + self.height_above_m <= 0:
            raise ConfigError("height_below_m and height_above_m must be ≥ 0 and not both 0")
        if self.tile_size < 16:
            raise ConfigError(f"tile_size must be ≥ 16, got {self.tile_size}")
        if self.lattice_px < 1:
            raise ConfigError(f"lattice_px must be ≥ 1, got {self.lattice_px}")
        if not 0.0 < self.threshold < 1.0:
            raise ConfigError(f"threshold must be in (0, 1), got {self.threshold}")

    @classmethod
    def robust(cls, **changes: Any) -> "ProbChangeParams":
        """The thesis's model with the extensions that matter on satellite data (docs/probchange.md).

        A "no consistent depth" hypothesis (``no_depth_prior`` 0.5), the visibility
        test and all pairs within an epoch; any field can be overridden (the
        symmetric test helped on small toy scenes but not on sample_aoi, see
        docs/probchange.md, so it stays off).
        """
        base = {"no_depth_prior": 0.5, "visibility": True, "pairs": "all"}
        base.update(changes)
        return cls(**base)

    _kind = "probchange"  # names the parameter set in ConfigError messages

    @property
    def radius(self) -> int:
        return self.window // 2

    @property
    def min_count(self) -> int:
        """Valid pixels a patch needs (at least 1)."""
        return max(1, int(math.ceil(self.min_valid_fraction * self.window**2)))
