"""Stereo products: :class:`PairDEM` (arrays) and its GeoTIFF (COG) form.

One pair-DEM per image pair, on the AOI grid. Bands (float32, NaN = nodata):

====== =========================================================================
z      ellipsoidal height, metres (WGS84); NaN where the match is not valid, except in holes
       narrower than the matching window, which hold interpolated heights (flag ``filled``)
score  the pair's match score (lower = better; MDL bits/pixel by default)
g      disparity per metre of height ‖∂u_a/∂z − ∂u_b/∂z‖, pixels/metre
valid  1 = valid match, 0 = rejected or unobserved
ncc    zero-mean NCC at the matched height
ssd    mean squared zero-mean difference at the matched height (8-bit units²)
flags  why a cell is invalid (bit set, see :data:`FLAGS`); 0 = valid
====== =========================================================================

Dataset tags carry the pair, the images, the cameras' names, the score's
definition, the parameters (JSON) and the geometry summary.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import UnsupportedFormatError
from ..geodesy import AOIGrid

#: reasons a cell is invalid (bit values of the ``flags`` band)
FLAGS = {
    "out_of_image": 1,  # no valid window in one image at any candidate height
    "low_texture": 2,  # a window's standard deviation < texture_min_snr · σ_n
    "not_unique": 4,  # ambiguous: another height matches almost as well (uniqueness test), or the height
    # stands alone — its surface patch is smaller than one matching window (neighbour agreement)
    "occluded": 8,  # loses its image pixel to a better match at another height (occlusion / left-right)
    "range_limit": 16,  # best height at the edge of the search range (or next to an invalid one)
    "low_ncc": 32,  # NCC below min_ncc
    "weak_geometry": 64,  # base/height ratio too small: height unreliable
    "filled": 128,  # invalid (other bits say why), but z holds a height interpolated from the valid
    # heights around: a hole narrower than the matching window (StereoParams.fill_holes)
}

#: ``flags`` value (not a bit: every bit set) of a cell a tiered run did not match (geocd run --screen: its
#: screen did not flag the tile)
FLAGS_NOT_EXAMINED = 255

BANDS = ("z", "score", "g", "valid", "ncc", "ssd", "flags")

SCORE_DEFINITION = (
    "MDL score (reconstruction, see geocd.stereo.scores): (L_match - L_ind)/n bits/pixel, "
    "L_ind = sum_j n/2 log2(s_j^2 + sigma_n^2), L_match = n/2 log2(s_t^2 + sigma_n^2) + "
    "(k-1) n/2 log2(v + sigma_n^2), k=2, the worst (largest) over the score_subwindow-cell "
    "sub-windows tiling the matching window; lower = better"
)


@dataclass
class PairDEM:
    """A dense height model from one image pair, on the AOI grid.

    Attributes
    ----------
    z_m : float32 (rows, cols)
        Ellipsoidal heights (m), NaN where not valid — except cells flagged ``filled``
        (invalid, in a hole narrower than the matching window), which hold heights interpolated
        from the valid ones around; ``valid`` is False there.
    score : float32 (rows, cols)
        Match score, lower = better (``meta["score_kind"]``: mdl, ncc or ssd).
    g_px_per_m : float32 (rows, cols)
        ‖∂u_a/∂z − ∂u_b/∂z‖: pixels of disparity per metre of height. A height
        difference Δz between matches p and q normalizes to
        ``Δz / sqrt(g_p⁻² + g_q⁻²)`` (one unit = one pixel of disparity).
    valid : bool (rows, cols)
    grid : AOIGrid
    name : str
        The pair's name ("<image a>__<image b>").
    camera_names : (str, str)
    ncc, ssd : float32 (rows, cols), alternative scores at the matched height
    flags : uint8 (rows, cols), bit set of :data:`FLAGS` (0 = valid)
    z_raw_m : float32 (rows, cols), optional
        The matched height before validity checks (NaN where nothing matched).
    mdl_window : float32 (rows, cols), optional
        The MDL score of the whole matching window (``score`` holds the worst of its
        sub-windows, ``StereoParams.score_subwindow``); in memory only, not written.
    epoch : str
    meta : dict
        step_m, noise_sigma, score_kind, base_height_median, levels, evaluations, ...
    """

    z_m: np.ndarray
    score: np.ndarray
    g_px_per_m: np.ndarray
    valid: np.ndarray
    grid: AOIGrid
    name: str = ""
    camera_names: tuple[str, str] = ("a", "b")
    ncc: np.ndarray | None = None
    ssd: np.ndarray | None = None
    flags: np.ndarray | None = None
    z_raw_m: np.ndarray | None = None
    mdl_window: np.ndarray | None = None
    epoch: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def completeness(self) -> float:
        """Fraction of grid cells with a valid match."""
        return float(np.mean(self.valid))

    def flag_counts(self) -> dict[str, int]:
        """Cells carrying each invalidity flag."""
        if self.flags is None:
            return {}
        return {k: int(np.count_nonzero(self.flags & v)) for k, v in FLAGS.items()}


def _nan(a: np.ndarray | None, shape) -> np.ndarray:
    return np.full(shape, np.nan, np.float32) if a is None else np.asarray(a, np.float32)


def write_pair_dem(
    path: os.PathLike | str, pair: PairDEM, *, tags: dict[str, Any] | None = None, overwrite: bool = True
) -> Path:
    """Write a pair-DEM as a COG (bands :data:`BANDS`) atomically."""
    from ..io.raster import write_cog

    shape = pair.grid.shape
    bands = {
        "z": _nan(pair.z_m, shape),
        "score": _nan(pair.score, shape),
        "g": _nan(pair.g_px_per_m, shape),
        "valid": np.asarray(pair.valid, np.float32),
        "ncc": _nan(pair.ncc, shape),
        "ssd": _nan(pair.ssd, shape),
        "flags": (np.zeros(shape, np.float32) if pair.flags is None else np.asarray(pair.flags, np.float32)),
    }
    units = {
        "z": "m (WGS84 ellipsoidal)",
        "score": f"{pair.meta.get('score_kind', 'mdl')} (lower = better)",
        "g": "px/m",
        "valid": "1 valid, 0 invalid",
        "ncc": "1",
        "ssd": "DN^2 (normalized 8-bit)",
        "flags": json.dumps(FLAGS),
    }
    t = {
        "geocd_product": "stereo_pair",
        "pair": pair.name,
        "cameras": json.dumps(list(pair.camera_names)),
        "epoch": pair.epoch,
        "score_definition": SCORE_DEFINITION,
        "vertical_datum": "ellipsoid",
        "meta": json.dumps(pair.meta, default=_json_default),
    }
    if tags:
        t.update(
            {
                k: (json.dumps(v, default=_json_default) if isinstance(v, (dict, list, tuple)) else v)
                for k, v in tags.items()
            }
        )
    return write_cog(
        path, bands, pair.grid, tags=t, band_tags=[{"units": units[b]} for b in BANDS], overwrite=overwrite
    )


def _json_default(o: Any):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def read_pair_dem(path: os.PathLike | str) -> PairDEM:
    """Read a pair-DEM written by :func:`write_pair_dem`."""
    from ..geodesy import as_crs
    from ..io.raster import _open

    with _open(path) as ds:
        names = ds.descriptions
        if not names or "z" not in names or "g" not in names:
            raise UnsupportedFormatError(
                f"{path} is not a geocd stereo pair-DEM (bands z, score, g, valid, ...); make it with `geocd stereo`"
            )
        arrs = {n: ds.read(i + 1).astype(np.float32) for i, n in enumerate(names) if n}
        grid = AOIGrid(as_crs(ds.crs), ds.transform, ds.width, ds.height)
        tags = ds.tags()
    meta = json.loads(tags.get("meta", "{}") or "{}")
    cams = tuple(json.loads(tags.get("cameras", '["a", "b"]')))
    valid = arrs.get("valid", np.isfinite(arrs["z"]).astype(np.float32)) > 0.5
    flags = arrs.get("flags")
    return PairDEM(
        z_m=arrs["z"],
        score=arrs.get("score", np.full(grid.shape, np.nan, np.float32)),
        g_px_per_m=arrs["g"],
        valid=valid & np.isfinite(arrs["z"]),
        grid=grid,
        name=tags.get("pair", Path(path).stem),
        camera_names=cams if len(cams) == 2 else ("a", "b"),
        ncc=arrs.get("ncc"),
        ssd=arrs.get("ssd"),
        flags=None if flags is None else np.nan_to_num(flags).astype(np.uint8),
        epoch=tags.get("epoch", ""),
        meta=meta,
    )
