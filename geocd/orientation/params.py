"""Parameters of the cross-epoch relative orientation (tie points + bias-compensating adjustment)."""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import ConfigError
from ..params import ParamsMixin


@dataclass(frozen=True)
class OrientationParams(ParamsMixin):
    """How tie points are found and the per-image corrections estimated.

    Attributes
    ----------
    enabled : "auto", True or False
        "auto" (default): on when the manifest has images of two or more epochs.
    model : "shift" or "affine"
        Per-image image-space correction (Grodecki & Dial: a shift absorbs the whole bias of an image of a few
        km; the affine adds a 2 × 2 linear part for longer strips).
    gauge : "mean" or "first"
        What removes the datum freedom: the mean correction over all images is held at zero (default: the result
        sits where the average of the RPCs puts it), or the first image is held fixed.
    prior_shift_px, prior_linear_px : float
        A-priori standard deviation of a shift and of the linear part (px at 1000 px from the centre); they fix the
        directions tie points cannot see (absolute height and tilt) and barely touch the others.
    max_offset_m : float
        Largest relative displacement between two images' orthos searched by the coarse pass (bias + relief).
    height_span_m : float
        Height range above/below the reference height in which tie points are searched along the epipolar direction.
    patch_px, block_px : int
        Half-size of the matching template and the block size in which the strongest corner is kept (ortho pixels).
    min_ncc : float
        Lowest NCC peak accepted for a tie point.
    min_points : int
        Fewest inlier observations per image for the correction to be applied.
    min_spread : float
        Smallest fraction of the AOI's area the convex hull of an image's inlier tie points must cover.
    min_correction_px : float
        Corrections are applied only when one of them reaches this size (px): below it the cameras already
        agree to within what the estimate resolves (on sample_aoi's exact cameras the estimates are 0.0–0.11 px;
        the stereo's own pointing correction uses the same 0.25 px floor).
    reject_k : float
        Observations whose reprojection residual exceeds ``reject_k`` robust sigmas (and 1 px) are outliers.
    max_ortho_px : int
        Cap on the ortho side in pixels (the posting is coarsened above it).
    """

    enabled: object = "auto"
    model: str = "shift"
    gauge: str = "mean"
    prior_shift_px: float = 10.0
    prior_linear_px: float = 2.0
    max_offset_m: float = 60.0
    height_span_m: float = 40.0
    patch_px: int = 12
    block_px: int = 24
    min_ncc: float = 0.6
    min_points: int = 20
    min_spread: float = 0.2
    min_correction_px: float = 0.25
    reject_k: float = 4.0
    max_ortho_px: int = 3000

    _kind = "orientation"

    def __post_init__(self) -> None:
        if self.enabled not in ("auto", True, False):
            raise ConfigError(f"orientation.enabled must be auto, true or false, got {self.enabled!r}")
        if self.model not in ("shift", "affine"):
            raise ConfigError(f"orientation.model must be 'shift' or 'affine', got {self.model!r}")
        if self.gauge not in ("mean", "first"):
            raise ConfigError(f"orientation.gauge must be 'mean' or 'first', got {self.gauge!r}")
        for k in ("prior_shift_px", "prior_linear_px", "max_offset_m", "height_span_m", "reject_k"):
            if not float(getattr(self, k)) > 0:
                raise ConfigError(f"orientation.{k} must be positive, got {getattr(self, k)!r}")
        if not (0.0 < self.min_ncc < 1.0):
            raise ConfigError(f"orientation.min_ncc must be in (0, 1), got {self.min_ncc}")
        if self.patch_px < 3 or self.block_px < 4 or self.min_points < 3:
            raise ConfigError("orientation.patch_px ≥ 3, block_px ≥ 4 and min_points ≥ 3 are needed")
        if not (0.0 <= self.min_spread <= 1.0):
            raise ConfigError(f"orientation.min_spread must be in [0, 1], got {self.min_spread}")

    @property
    def n_params(self) -> int:
        return 2 if self.model == "shift" else 6
