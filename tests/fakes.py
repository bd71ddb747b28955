"""Small stand-ins shared by tests."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Rec:
    """A pair-DEM as the self-consistency code reads it: heights, match scores, the height-to-disparity
    factor and validity per cell (a :class:`~geocd.stereo.products.PairDEM` without the files)."""

    z_m: np.ndarray
    score: np.ndarray
    g_px_per_m: np.ndarray
    valid: np.ndarray
    grid: object = None
    name: str = "rec"
