"""Probabilistic structure-change detection without reconstruction (Sakurada's thesis, ch. 5; issue 8).

Depth is never decided: along each reference ray, one epoch's within-epoch patch
dissimilarities give a depth density p(d) ∝ exp(−s_d/σ); the other epoch's
within-epoch dissimilarities s'_d along the same ray are compared against it and
the posterior p(c = 1 | s'_1..s'_n) is the change probability (eqs. 5.5–5.11, in
the log domain). Patches are only compared within an epoch, so illumination
changes between epochs do not matter.

Public API
----------
* :func:`detect_keyframe` — rays of every key-frame pixel (any camera kind: bins
  uniform in disparity = inverse depth for frame cameras, height for RPC views)
  → :class:`KeyFrameResult` (``.to_grid(grid)`` puts it on an AOI grid).
* :func:`detect_objectspace` — vertical rays of every AOI cell (height bins),
  built on :class:`geocd.stereo.PlaneSweep` → :class:`ProbChangeResult`.
* :class:`View`, :func:`make_view` — an image's normalized band chips + camera.
* :class:`ProbChangeParams` — every tunable, frozen.
* Model (:mod:`.likelihood`): :func:`depth_log_prob`, :func:`change_log_likelihood_ratio`,
  :func:`posterior_change`, :func:`fit_half_laplace` (σ per §5.3.5), :class:`NoiseModel`.
* Files: :func:`run_probchange` (manifest → products; ``geocd probchange`` CLI),
  :func:`write_probchange_products`.
"""

from .engine import View, make_pairs, make_view  # noqa: E402
from .keyframe import KeyFrameResult, detect_keyframe, ray_hypotheses  # noqa: E402
from .likelihood import (
    NoiseModel,
    change_log_likelihood_ratio,
    change_probability_direct,  # noqa: E402
    depth_log_prob,
    fit_half_laplace,
    posterior_change,
    uniform_range,
)
from .objectspace import ProbChangeResult, detect_objectspace  # noqa: E402
from .params import ProbChangeParams  # noqa: E402


def __getattr__(name):  # lazy: products and the pipeline import I/O
    if name in ("write_probchange_products", "write_keyframe_products"):
        from . import products

        return getattr(products, name)
    if name in ("run_probchange", "load_views"):
        from . import pipeline

        return getattr(pipeline, name)
    raise AttributeError(name)


__all__ = [
    "KeyFrameResult",
    "NoiseModel",
    "ProbChangeParams",
    "ProbChangeResult",
    "View",
    "change_log_likelihood_ratio",
    "change_probability_direct",
    "depth_log_prob",
    "detect_keyframe",
    "detect_objectspace",
    "fit_half_laplace",
    "make_pairs",
    "make_view",
    "posterior_change",
    "ray_hypotheses",
    "uniform_range",
    "write_probchange_products",
    "write_keyframe_products",
    "run_probchange",
    "load_views",
]
