"""Cross-epoch relative orientation: automatic tie points between all images of all epochs and a
bias-compensating adjustment (per-image image-space shift or affine, Grodecki & Dial), applied
through :class:`geocd.camera.corrected.CorrectedCamera`."""

from .adjust import OrientationResult, adjust, residual_norms  # noqa: F401
from .params import OrientationParams  # noqa: F401
from .pipeline import OrientationWarning, corrected_manifest, orient_images, orient_manifest  # noqa: F401
from .tiepoints import OrthoView, TiePoints, find_tie_points, ortho_at_height, relief_displacement  # noqa: F401
