"""The multitemporal marked point process and its optimisation by multiple birth and death.

A building seen from above is a union of rectangles u = (c_x, c_y, e_L, e_l, θ, ξ) with
ξ ∈ {*, 1, 2} (codes 0, 1, 2): present on both images, only on image 1 (demolished), only on image 2
(new). The configuration ω minimises (paper eq. 1)

    Φ_D(ω) = Σ_u A_D(u) + γ Σ_{u~v} I(u, v)
    A_D(u) = 1[ξ∈{1,*}] φ¹(u) + 1[ξ∈{2,*}] φ²(u)
             + γ_ξ (1[ξ=*] mean_{R_u}(1 − B) + 1[ξ∈{1,2}] mean_{R_u} B)
             + γ_3D (1[ξ=*] mean_{R_u} c + 1[ξ∈{1,2}] mean_{R_u}(1 − c))        (beyond the paper; c = 3-D change)

with φ^i(u) the image-i object energy: feature energies through Q, AND (max) within a prototype,
OR (min) across prototypes; I(u, v) the cell-count Jaccard overlap of rectangles sharing a time layer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..errors import ConfigError, GridError
from ..progress import Progress, ensure_progress
from . import _kernels as K
from .features import ImageFeatures
from .params import MPPParams, parse_prototypes

BOTH, ONLY_1, ONLY_2 = 0, 1, 2
#: column of the raw features appended after the kernel's: share of planar DSM cells in the rectangle's core
F_PLANAR = K.N_FEATURES
#: … and the share of the outline along which the DSM steps down from inside to outside
F_STEP = K.N_FEATURES + 1
#: … and the share of its cells standing more than min_height above the ground, rough cells included (absence)
F_STANDING = K.N_FEATURES + 2
N_RAW = K.N_FEATURES + 3
XI_NAMES = {BOTH: "unchanged", ONLY_1: "demolished", ONLY_2: "new"}


def Q(x: np.ndarray, d0: float, D: float) -> np.ndarray:
    """The paper's transfer function: 1 − x/d0 below d0 (repulsive), exp(−(x − d0)/D) − 1 above (attractive)."""
    x = np.asarray(x, np.float64)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        below = 1.0 - x / d0 if d0 > 0 else np.zeros_like(x)
        above = np.exp(-(x - d0) / max(D, 1e-12)) - 1.0
    out = np.where(x < d0, below, above)
    return np.where(np.isfinite(x), out, 1.0)


@dataclass
class ImageTerm:
    """How one image scores a rectangle: its features, prototypes and measured thresholds."""

    features: ImageFeatures
    prototypes: list[list[str]]
    d_gradient: float
    D_gradient: float


def auto_prototypes(f: ImageFeatures, params: MPPParams) -> list[list[str]]:
    """The paper's models: grey → gradient AND homogeneity; colour → (gradient AND shadow) OR colour
    (homogeneity instead of shadow when the image has too few shadows). With ``params.height == "and"``
    every prototype also needs the height term, and (gradient AND height) and (homogeneity AND height) are
    two more prototypes; features the image lacks are dropped."""
    if params.prototypes != "auto":
        protos = parse_prototypes(params.prototypes)
    elif f.colour_mask is None:
        protos = [["gradient", "homogeneity"]]
    elif f.shadow_mask is not None:
        protos = [["gradient", "shadow"], ["colour"]]
    else:
        protos = [["gradient", "homogeneity"], ["colour"]]
    have = {"gradient", "homogeneity"}
    if f.colour_mask is not None:
        have.add("colour")
    if f.shadow_mask is not None:
        have.add("shadow")
    if f.ndsm is not None:
        have.add("height")
    if f.planar is not None and params.planarity in ("core", "both"):
        have.add("planarity")
    if f.ndsm is not None and params.step == "and" and math.isfinite(f.step_min_m):
        have.add("step")
    if params.height == "and" and "height" in have:
        # the height term is required, and any one image cue confirms it: every image prototype, the
        # gradient alone or the roof homogeneity alone, each AND height (a raised block that also looks like
        # a building: trees are raised but neither outlined by straight edges nor homogeneous); the raised
        # block must also be planar (roof facets), which a tree crown is not
        hp = ["height", "planarity"] if "planarity" in have else ["height"]
        if "step" in have:  # … with steep edges: the surface steps down along most of the outline
            hp = hp + ["step"]
        protos = [p + hp for p in protos] + [["gradient"] + hp, ["homogeneity"] + hp]
    out = []
    for p in protos:
        q = [x for x in p if x in have]
        if q and q not in out:
            out.append(q)
    return out or [["gradient"]]


def random_rectangles(
    f: ImageFeatures, n: int, smin: float, smax: float, sigma_theta_deg: float, rng: np.random.Generator
) -> np.ndarray:
    """Rectangles drawn like births but uniformly over the valid cells (the data thresholds' reference)."""
    ii, jj = np.nonzero(f.valid)
    k = rng.integers(0, ii.size, n)
    th = np.radians(f.mode_deg[ii[k], jj[k]] + rng.normal(0.0, sigma_theta_deg, n))
    return np.column_stack(
        [jj[k].astype(float), ii[k].astype(float), rng.uniform(smin, smax, n), rng.uniform(smin, smax, n), th]
    )


class EnergyModel:
    """Data energies of rectangles on one or two images (arrays on one AOI grid).

    Parameters
    ----------
    features : one ImageFeatures per image (1 or 2)
    posting_m : grid posting (m)
    similarity : B map (1 = unchanged texture), needed for the joint model
    change_prior : 3-D change evidence c ∈ [0, 1] on the grid (optional)
    """

    def __init__(
        self,
        features: Sequence[ImageFeatures],
        posting_m: float,
        params: MPPParams = MPPParams(),
        *,
        similarity: np.ndarray | None = None,
        change_prior: np.ndarray | None = None,
        prototypes: Sequence[list[list[str]]] | None = None,
    ):
        if not 1 <= len(features) <= 2:
            raise ConfigError("the model takes one or two images")
        shape = features[0].grey.shape
        for f in features:
            if f.grey.shape != shape:
                raise GridError(
                    f"images on different grids: {[x.grey.shape for x in features]}; orthorectify or "
                    "resample them onto one AOI grid first"
                )
        self.shape = shape
        self.params = params
        self.posting_m = float(posting_m)
        self.smin = params.side_min_m / posting_m
        self.smax = params.side_max_m / posting_m
        self.edge_w = max(1.0, params.edge_width_m / posting_m)
        self.ring_w = max(2.0, params.ring_m / posting_m)
        self.shadow_w = max(2.0, params.shadow_ring_m / posting_m)
        self.gradient_column = K.F_GRADIENT if params.edge_mode == "mean" else K.F_GRADIENT_SIDES
        self.similarity = None if similarity is None else np.asarray(similarity, np.float32)
        self.change_prior = None if change_prior is None else np.asarray(change_prior, np.float32)
        self._hcache: dict = {}
        rng = np.random.default_rng(params.seed + 7919)
        self.terms: list[ImageTerm] = []
        for k, f in enumerate(features):
            protos = list(prototypes[k]) if prototypes is not None else auto_prototypes(f, params)
            ref = random_rectangles(f, 3000, self.smin, self.smax, params.sigma_theta_deg, rng)
            lam = self._raw_one(f, ref, np.inf)[:, self.gradient_column]  # the gradient only: no homogeneity
            d = float(np.quantile(lam, params.gradient_quantile))
            D = float(np.quantile(lam, 0.99)) - d
            self.terms.append(ImageTerm(f, protos, d, max(D, 0.1 * d, 1e-9)))
        # homogeneity is only worth computing where the gradient term can be attractive, when every
        # prototype that uses homogeneity also uses the gradient (AND): the object is repulsive otherwise
        self.gates = []
        for t in self.terms:
            gated = all("gradient" in p for p in t.prototypes if "homogeneity" in p)
            self.gates.append(t.d_gradient if gated else -np.inf)

    # --- raw features ------------------------------------------------------------------------
    def _height_map(self, f: ImageFeatures) -> np.ndarray:
        """The nDSM the height term reads: with ``planarity == "roof"``, rough cells (tree crowns) count as
        not raised, so a building is a raised *planar* block."""
        if f.ndsm is None:
            return np.zeros((0, 0), np.float32)
        if self.params.planarity not in ("roof", "both") or f.planar is None:
            return f.ndsm
        key = id(f)
        if key not in self._hcache:
            self._hcache[key] = np.where(f.planar == 0, np.float32(0.0), f.ndsm).astype(np.float32)
        return self._hcache[key]

    def ring_in(self, f: ImageFeatures) -> float:
        """The outer limit (cells) of the DSM's blurred-wall band around a rectangle: within it, a cell of the
        height ring ("the ring outside is ground") only needs to be below half the rectangle's height. With
        ``wall_blur="measured"``: where this image's DSM walls fall to 10 % of their height outside its edges
        (:func:`~geocd.mpp.features.wall_blur_m`); otherwise the edge band (the plain ground test)."""
        if self.params.wall_blur == "measured" and math.isfinite(f.wall_out_m):
            return max(self.edge_w, f.wall_out_m / self.posting_m)
        return self.edge_w

    def core_in(self, f: ImageFeatures) -> float:
        """How deep inside a rectangle's sides (cells) the raised fraction starts being counted: with
        ``wall_blur="measured"``, past the DSM's blurred wall (where it reaches 90 % of its height inside this
        image's edges: the ramp is low or rough, and rough cells do not count as raised); otherwise 0."""
        if self.params.wall_blur == "measured" and math.isfinite(f.wall_in_m):
            return f.wall_in_m / self.posting_m
        return 0.0

    def _raw_one(self, f: ImageFeatures, rects: np.ndarray, gate: float) -> np.ndarray:
        empty_u8 = np.zeros((0, 0), np.uint8)
        out = np.empty((rects.shape[0], K.N_FEATURES))
        sdx, sdy = f.shadow_dir if f.shadow_dir is not None else (0.0, 0.0)
        K.rect_features(
            np.ascontiguousarray(rects, np.float64),
            f.grey,
            f.valid,
            f.grad_mag,
            f.grad_ori,
            f.colour_mask if f.colour_mask is not None else empty_u8,
            f.shadow_mask if f.shadow_mask is not None else empty_u8,
            float(sdx),
            float(sdy),
            self._height_map(f),
            float(self.params.min_height_m),
            float(self.edge_w),
            float(self.ring_w),
            float(self.shadow_w),
            float(3.0 * f.noise_sigma),
            float(self.params.flood_spread),
            float(gate),
            float(self.ring_in(f)),
            float(self.core_in(f)),
            out,
        )
        out = np.column_stack([out, np.full((rects.shape[0], N_RAW - K.N_FEATURES), np.nan)])
        if f.ndsm is not None and self.params.step != "off" and math.isfinite(f.step_min_m) and rects.shape[0]:
            st = np.empty(rects.shape[0])
            K.rect_steps(
                np.ascontiguousarray(rects, np.float64),
                f.ndsm,
                float(f.step_min_m),
                0.5,
                float(self.edge_w),
                float(self.ring_w),
                float(self.ring_w),
                st,
            )
            out[:, F_STEP] = st
        if f.planar is not None and rects.shape[0]:
            # the core of the rectangle, clear of the walls' edge band (where a DSM's walls are never planar)
            core = np.array(rects, np.float64, copy=True)
            core[:, 2:4] = np.maximum(core[:, 2:4] - 2.0 * self.edge_w, 1.0)
            m = np.empty(rects.shape[0])
            K.rect_means(core, f.planar, m)
            out[:, F_PLANAR] = m
        if f.ndsm is not None and self.params.absence != "off" and rects.shape[0]:
            key = ("standing", id(f))
            if key not in self._hcache:
                with np.errstate(invalid="ignore"):
                    self._hcache[key] = np.where(np.isfinite(f.ndsm), f.ndsm > self.params.min_height_m, np.nan).astype(
                        np.float32
                    )
            m = np.empty(rects.shape[0])
            K.rect_means(np.ascontiguousarray(rects, np.float64), self._hcache[key], m)
            out[:, F_STANDING] = m
        return out

    def raw(self, rects: np.ndarray, *, for_energy: bool = False) -> dict[str, np.ndarray]:
        """Raw features of rectangles: per image (``img0``, ``img1``) and over the pair (``change``, ``c3d``).

        ``for_energy``: the homogeneity features (the roof halves' flood fill, most of the kernel's time) only
        of the rectangles whose φ they can change (:meth:`_raw_lazy`), NaN for the others: φ and
        A_D are the same, only the homogeneity columns themselves differ."""
        if for_energy:
            out = {f"img{k}": self._raw_lazy(k, rects) for k in range(len(self.terms))}
        else:
            out = {f"img{k}": self._raw_one(t.features, rects, self.gates[k]) for k, t in enumerate(self.terms)}
        r = np.ascontiguousarray(rects, np.float64)
        if self.similarity is not None:
            m = np.empty(rects.shape[0])
            K.rect_means(r, 1.0 - self.similarity, m)
            out["change"] = np.where(np.isfinite(m), m, 0.5)
        if self.change_prior is not None:
            m = np.empty(rects.shape[0])
            K.rect_means(r, self.change_prior, m)
            out["c3d"] = np.where(np.isfinite(m), m, 0.5)
        return out

    def _raw_lazy(self, k: int, rects: np.ndarray) -> np.ndarray:
        """:meth:`_raw_one` of image ``k`` with the homogeneity features computed only where they can change φ.

        When a prototype without homogeneity exists, φ often does not depend on it: φ = min over prototypes of
        the max of their energies, so φ is non-decreasing in the homogeneity energy (in [−1, 1]), and when φ is
        the same with −1 and with +1 it is the same with any value. Those rectangles keep NaN (energy +1)."""
        t = self.terms[k]
        if all("homogeneity" in proto for proto in t.prototypes):  # then φ depends on it almost everywhere
            return self._raw_one(t.features, rects, self.gates[k])
        out = self._raw_one(t.features, rects, np.inf)  # an infinite gate: no homogeneity
        if not any("homogeneity" in proto for proto in t.prototypes):
            return out
        lo = out.copy()
        lo[:, K.F_KURTOSIS] = 1e300  # far above both thresholds: the homogeneity energy's lowest value, −1
        lo[:, K.F_COMPLETE] = 1e300
        need = np.flatnonzero(self.phi(k, lo) != self.phi(k, out))
        if need.size:
            sub = self._raw_one(t.features, rects[need], self.gates[k])
            out[need, K.F_KURTOSIS] = sub[:, K.F_KURTOSIS]
            out[need, K.F_COMPLETE] = sub[:, K.F_COMPLETE]
        return out

    # --- energies ------------------------------------------------------------------------------
    def feature_energy(self, k: int, raw: np.ndarray, names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """φ of every feature of image ``k`` (before combination); of the features ``names`` only when given."""
        t = self.terms[k]
        p = self.params
        terms = {
            "gradient": lambda: Q(raw[:, self.gradient_column], t.d_gradient, t.D_gradient),
            "homogeneity": lambda: np.maximum(
                Q(raw[:, K.F_KURTOSIS], p.kurtosis_threshold, 0.5), Q(raw[:, K.F_COMPLETE], 0.5, 0.25)
            ),
            "colour": lambda: np.maximum(Q(raw[:, K.F_COLOUR_IN], 0.5, 0.25), Q(raw[:, K.F_COLOUR_OUT], 0.5, 0.25)),
            "shadow": lambda: np.maximum(Q(raw[:, K.F_SHADOW_IN], 0.5, 0.25), Q(raw[:, K.F_SHADOW_OUT], 0.5, 0.25)),
            "height": lambda: np.maximum(Q(raw[:, K.F_RAISED_IN], 0.5, 0.25), Q(raw[:, K.F_RAISED_OUT], 0.5, 0.25)),
            "planarity": lambda: Q(raw[:, F_PLANAR], 0.5, 0.25),
            "step": lambda: Q(raw[:, F_STEP], 0.5, 0.25),
        }
        e = {name: f() for name, f in terms.items() if names is None or name in names}
        if "height" in e and p.step == "ring" and np.isfinite(raw[:, F_STEP]).any():
            # raised inside, and outside either ground or a step down (a block among raised neighbours)
            e["height"] = np.maximum(
                Q(raw[:, K.F_RAISED_IN], 0.5, 0.25),
                np.minimum(Q(raw[:, K.F_RAISED_OUT], 0.5, 0.25), e["step"] if "step" in e else terms["step"]()),
            )
        return e

    def phi(self, k: int, raw: np.ndarray) -> np.ndarray:
        """φ^k(u): AND (max) within a prototype, OR (min) across prototypes; +1 when under half is observed."""
        e = self.feature_energy(k, raw, {f for proto in self.terms[k].prototypes for f in proto})
        ph = np.min(
            np.stack([np.max(np.stack([e[f] for f in proto]), axis=0) for proto in self.terms[k].prototypes]), axis=0
        )
        return np.where(raw[:, K.F_VALID] >= 0.5, ph, 1.0)

    def data_energy(
        self, raw: dict[str, np.ndarray], xi: np.ndarray, phis: Sequence[np.ndarray] | None = None
    ) -> np.ndarray:
        """A_D(u) for labels ``xi`` (0 = both, 1 = image 1 only, 2 = image 2 only); ``phis``: the images' φ of
        ``raw`` when already computed."""
        xi = np.asarray(xi)
        p = self.params
        if phis is None:
            phis = [self.phi(k, raw[f"img{k}"]) for k in range(len(self.terms))]
        if len(phis) == 1:
            return phis[0]
        a = np.where(xi != ONLY_2, phis[0], 0.0) + np.where(xi != ONLY_1, phis[1], 0.0)
        if "change" in raw and p.gamma_change:
            a = a + p.gamma_change * np.where(xi == BOTH, raw["change"], 1.0 - raw["change"])
        if "c3d" in raw and p.gamma_3d:
            a = a + p.gamma_3d * np.where(xi == BOTH, raw["c3d"], 1.0 - raw["c3d"])
        if p.absence == "height":
            # a change label says the object is absent on the other date: that date's DSM must show ground
            # under at least half of it (NaN, no DSM data there: no evidence, no penalty)
            for k, x in ((0, ONLY_2), (1, ONLY_1)):
                r = raw[f"img{k}"][:, F_STANDING]
                a = a + np.where((xi == x) & np.isfinite(r), np.maximum(0.0, 2.0 * r - 1.0), 0.0)
        return a


# ---------------------------------------------------------------------------------------------
# multiple birth and death
# ---------------------------------------------------------------------------------------------
@dataclass
class MPPResult:
    """The optimised configuration.

    Attributes
    ----------
    rects : float64 (n, 5) — c_x, c_y (cells, array-index coordinates), e_L, e_l (cells), θ (radians)
    xi : int8 (n,) — 0 both dates (unchanged), 1 first date only (demolished), 2 second date only (new)
    energy : float64 (n,) — A_D(u)
    phi : float64 (n, n_images) — φ^i(u)
    confidence : float64 (n,) — % : the Gibbs probability of the object given the others (β = 1)
    xi_confidence : float64 (n,) — % : probability of its ξ label among the three (same model)
    iterations, converged, births, energy_total, history
    object_id : int64 (n,) or None — the annealed object each rectangle belongs to: the two rectangles of an
        L cut from one object (``MPPParams.edge_fit_carve``) share it and carry its energies and confidences
        (``energy_total`` counts the object once); None: every rectangle is its own object
    """

    rects: np.ndarray
    xi: np.ndarray
    energy: np.ndarray
    phi: np.ndarray
    confidence: np.ndarray
    xi_confidence: np.ndarray
    iterations: int = 0
    converged: bool = False
    births: int = 0
    energy_total: float = 0.0
    history: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    object_id: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.rects.shape[0])


def _pairs(rects: np.ndarray, xi: np.ndarray, new: np.ndarray, old: np.ndarray, reach: float):
    """Candidate pairs (new–old and new–new) whose circumscribed circles meet and who share a time layer."""
    from scipy.spatial import cKDTree

    if new.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ids = np.concatenate([new, old])
    pairs = cKDTree(rects[ids, :2]).query_pairs(reach, output_type="ndarray")
    if pairs.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pairs = pairs[(pairs[:, 0] < new.size) | (pairs[:, 1] < new.size)]
    pi, pj = ids[pairs[:, 0]].astype(np.int64), ids[pairs[:, 1]].astype(np.int64)
    rad = 0.5 * np.hypot(rects[:, 2], rects[:, 3])
    close = np.hypot(*(rects[pi, :2] - rects[pj, :2]).T) <= rad[pi] + rad[pj] + 1.0
    share = (xi[pi] == xi[pj]) | (xi[pi] == BOTH) | (xi[pj] == BOTH)
    keep = close & share
    pi, pj = np.minimum(pi[keep], pj[keep]), np.maximum(pi[keep], pj[keep])
    order = np.lexsort((pj, pi))
    return pi[order], pj[order]


def _csr(n: int, pi: np.ndarray, pj: np.ndarray, w: np.ndarray):
    a = np.concatenate([pi, pj])
    b = np.concatenate([pj, pi])
    ww = np.concatenate([w, w])
    order = np.lexsort((b, a))
    a, b, ww = a[order], b[order], ww[order]
    indptr = np.zeros(n + 1, np.int64)
    np.add.at(indptr, a + 1, 1)
    return np.cumsum(indptr), b.astype(np.int64), ww.astype(np.float64)


def optimize(
    model: EnergyModel,
    params: MPPParams = MPPParams(),
    *,
    allowed_xi: Sequence[int] | None = None,
    progress: Progress | None = None,
) -> MPPResult:
    """Multiple birth and death with annealing (paper §5), then a greedy clean-up of objects that do not
    lower the energy (the target is argmin Φ_D).

    Parameters
    ----------
    allowed_xi : labels newborns may take (default: {*, 1, 2} with two images, {1} with one)
    """
    prog = ensure_progress(progress)
    two = len(model.terms) == 2
    allowed = np.array(
        allowed_xi if allowed_xi is not None else ((BOTH, ONLY_1, ONLY_2) if two else (ONLY_1,)), np.int8
    )
    rng = np.random.default_rng(params.seed)
    H, W = model.shape
    f = [t.features for t in model.terms]
    valid = f[0].valid if not two else (f[0].valid | f[1].valid)
    births_map = {ONLY_1: f[0].birth, ONLY_2: f[1].birth if two else f[0].birth}
    births_map[BOTH] = np.maximum(births_map[ONLY_1], births_map[ONLY_2])
    mode_map = {ONLY_1: f[0].mode_deg, ONLY_2: f[1].mode_deg if two else f[0].mode_deg}
    mode_map[BOTH] = np.where(births_map[ONLY_1] >= births_map[ONLY_2], mode_map[ONLY_1], mode_map[ONLY_2])
    a_typ = (params.window / model.posting_m) ** 2
    base_rate = params.births_per_area / a_typ
    reach = math.sqrt(2.0) * model.smax + 2.0

    cap = 4096
    rects = np.zeros((cap, 5))
    xi = np.zeros(cap, np.int8)
    energy = np.zeros(cap)
    phis = np.zeros((cap, len(model.terms)))
    areas = np.zeros(cap)
    cell = np.zeros(cap, np.int64)  # the cell each object was born on (one object per cell)
    alive = np.zeros(cap, bool)
    centred = np.zeros((H, W), bool)
    n = 0
    pi_all = np.zeros(0, np.int64)
    pj_all = np.zeros(0, np.int64)
    w_all = np.zeros(0)
    beta, delta = params.beta0, params.delta0
    history = []
    converged = False
    total_births = 0
    it = 0
    for it in range(1, params.max_iter + 1):
        # --- birth -------------------------------------------------------------------------
        draw_xi = allowed[rng.integers(0, allowed.size, H * W)].reshape(H, W)
        u = rng.random((H, W))
        pb = np.select([draw_xi == BOTH, draw_xi == ONLY_1], [births_map[BOTH], births_map[ONLY_1]], births_map[ONLY_2])
        born = (u < delta * base_rate * pb) & valid & ~centred
        bi, bj = np.nonzero(born)
        nb = bi.size
        sides = rng.uniform(model.smin, model.smax, (nb, 2))
        dx = draw_xi[bi, bj]
        m_deg = np.select(
            [dx == BOTH, dx == ONLY_1], [mode_map[BOTH][bi, bj], mode_map[ONLY_1][bi, bj]], mode_map[ONLY_2][bi, bj]
        )
        theta = np.radians(m_deg + rng.normal(0.0, params.sigma_theta_deg, nb))
        theta = (theta + np.pi / 2) % np.pi - np.pi / 2
        new_rects = np.column_stack([bj.astype(float), bi.astype(float), sides[:, 0], sides[:, 1], theta])
        new_xi = draw_xi[bi, bj].astype(np.int8)
        if params.snap_births > 0 and nb:
            snap = rng.random(nb) < params.snap_births
            use2 = (new_xi == ONLY_2) | ((new_xi == BOTH) & (births_map[ONLY_2][bi, bj] > births_map[ONLY_1][bi, bj]))
            for k, sel in ((0, snap & ~use2), (1 if two else 0, snap & use2)):
                if sel.any():
                    fk = f[k]
                    sub = np.ascontiguousarray(new_rects[sel])
                    if fk.ndsm is not None:
                        # extents from the height map, then each side onto the image's strongest edge within
                        # the width of a stereo DSM's blurred walls (the outer ring, 2 m)
                        K.snap_rects_height(
                            sub, fk.ndsm, float(params.min_height_m), float(model.smin), float(model.smax)
                        )
                        K.refine_sides(sub, fk.grad_mag, fk.grad_ori, float(model.ring_w), 9)
                        sub[:, 2:4] = np.clip(sub[:, 2:4], model.smin, model.smax)
                    else:
                        K.snap_rects(
                            sub, fk.grad_mag, fk.grad_ori, float(fk.edge_level), float(model.smin), float(model.smax)
                        )
                    new_rects[sel] = sub
        if params.perturb_births and n:
            par = np.flatnonzero(alive[:n])
            par = par[rng.random(par.size) < delta]
            if par.size:
                pr = rects[par].copy()
                pr[:, :2] = np.round(pr[:, :2] + rng.integers(-1, 2, (par.size, 2)))
                pr[:, 2:4] = np.clip(pr[:, 2:4] + rng.uniform(-2.0, 2.0, (par.size, 2)), model.smin, model.smax)
                pr[:, 4] = (pr[:, 4] + np.radians(rng.uniform(-3.0, 3.0, par.size)) + np.pi / 2) % np.pi - np.pi / 2
                ii = np.clip(pr[:, 1].astype(int), 0, H - 1)
                jj = np.clip(pr[:, 0].astype(int), 0, W - 1)
                free = ~centred[ii, jj] & valid[ii, jj] & ~born[ii, jj]
                _, first = np.unique(ii[free] * W + jj[free], return_index=True)
                sel = np.flatnonzero(free)[np.sort(first)]
                new_rects = np.concatenate([new_rects, pr[sel]])
                new_xi = np.concatenate([new_xi, xi[par[sel]]])
                bi = np.concatenate([bi, ii[sel]])
                bj = np.concatenate([bj, jj[sel]])
                nb = bi.size
        if n + nb > cap:
            grow = max(cap, n + nb - cap + 1024)
            rects = np.concatenate([rects, np.zeros((grow, 5))])
            xi = np.concatenate([xi, np.zeros(grow, np.int8)])
            energy = np.concatenate([energy, np.zeros(grow)])
            phis = np.concatenate([phis, np.zeros((grow, phis.shape[1]))])
            areas = np.concatenate([areas, np.zeros(grow)])
            cell = np.concatenate([cell, np.zeros(grow, np.int64)])
            alive = np.concatenate([alive, np.zeros(grow, bool)])
            cap += grow
        idx = np.arange(n, n + nb)
        if nb:
            raw = model.raw(new_rects, for_energy=True)
            rects[idx] = new_rects
            xi[idx] = new_xi
            ph = [model.phi(k, raw[f"img{k}"]) for k in range(len(model.terms))]
            energy[idx] = model.data_energy(raw, new_xi, ph)
            phis[idx] = np.column_stack(ph)
            areas[idx] = raw["img0"][:, K.F_AREA]
            cell[idx] = bi * W + bj
            alive[idx] = True
            centred[bi, bj] = True
        old = np.flatnonzero(alive[:n])
        n += nb
        total_births += nb
        # --- overlaps of the newborns -------------------------------------------------------
        pi, pj = _pairs(rects[:n], xi[:n], idx, old, reach)
        w = np.empty(pi.size)
        if pi.size:
            K.pair_overlaps(rects[:n], pi, pj, areas[:n], H, W, w)
        keep_old = alive[pi_all] & alive[pj_all] if pi_all.size else np.zeros(0, bool)
        pi_all = np.concatenate([pi_all[keep_old], pi[w > 0]])
        pj_all = np.concatenate([pj_all[keep_old], pj[w > 0]])
        w_all = np.concatenate([w_all[keep_old], w[w > 0]])
        # --- death --------------------------------------------------------------------------
        live = np.flatnonzero(alive[:n])
        order = live[np.lexsort((live, -energy[live]))]  # A_D decreasing, ties by index
        indptr, nbr, ww = _csr(n, pi_all, pj_all, w_all)
        before = alive[:n].copy()
        rand = rng.random(n)
        K.death_pass(
            order, indptr, nbr, ww, energy[:n], alive[:n], float(beta), float(delta), float(params.gamma_overlap), rand
        )
        died = before & ~alive[:n]
        centred.ravel()[cell[:n][died]] = False
        newborn = np.zeros(n, bool)
        newborn[idx] = True
        n_alive = int(alive[:n].sum())
        history.append(
            {
                "iteration": it,
                "beta": beta,
                "delta": delta,
                "births": int(nb),
                "deaths": int(died.sum()),
                "objects": n_alive,
            }
        )
        prog(min(it / params.max_iter, 0.99), f"iteration {it}: {n_alive} objects")
        if it >= params.min_iter and nb > 0 and np.array_equal(died, newborn):
            converged = True
            break
        beta *= params.beta_factor
        delta *= params.delta_factor
        # compact: drop the dead to keep arrays small
        if n > 2 * max(n_alive, 256):
            keepi = np.flatnonzero(alive[:n])
            remap = -np.ones(n, np.int64)
            remap[keepi] = np.arange(keepi.size)
            m = keepi.size
            rects[:m], xi[:m], energy[:m], phis[:m] = rects[keepi], xi[keepi], energy[keepi], phis[keepi]
            areas[:m], cell[:m] = areas[keepi], cell[keepi]
            alive[:m] = True
            alive[m:n] = False
            ok = (remap[pi_all] >= 0) & (remap[pj_all] >= 0)
            pi_all, pj_all, w_all = remap[pi_all[ok]], remap[pj_all[ok]], w_all[ok]
            n = m
    # --- sub-cell edge fit of the kept objects ---------------------------------------------------
    fitted = 0
    fit_counts = (0, 0)
    fit_notes = []
    with_dsm = all(t.features.ndsm is not None for t in model.terms)
    if params.edge_fit == "image" or (params.edge_fit == "joint" and with_dsm):  # "joint" needs the DSMs
        live = np.flatnonzero(alive[:n])
        if live.size:
            got = fit_edges(model, rects[live], xi[live], energy[live], params)
            fitted = int(got["accepted"].sum())
            fit_counts = (int(got["moved"].sum()), int(got["energy_not_worse"].sum()))
            fit_notes.append(
                f"edge fit ({params.edge_fit}): {fit_counts[0]} objects refitted after the "
                f"annealing, {fitted} kept (sides and turns: edge evidence not weaker, still attractive"
                + (
                    f"; {int(got['grown'].sum())} of them grown over the raised block, still attractive"
                    if params.edge_fit_grow and params.edge_fit == "joint"
                    else ""
                )
                + (f"; {int(got['turned'].sum())} of them turned" if params.edge_fit_rotate else "")
                + f"); A_D not raised for {fit_counts[1]}"
            )
            if fitted:
                sel = live[got["accepted"]]
                rects[sel] = got["rects"][got["accepted"]]
                energy[sel] = got["energy"][got["accepted"]]
                phis[sel] = got["phi"][got["accepted"]]
                areas[sel] = got["area"][got["accepted"]]
                pi, pj = _pairs(rects[:n], xi[:n], live, np.zeros(0, np.int64), reach)
                w = np.empty(pi.size)
                if pi.size:
                    K.pair_overlaps(rects[:n], pi, pj, areas[:n], H, W, w)
                pi_all, pj_all, w_all = pi[w > 0], pj[w > 0], w[w > 0]
    # --- clean-up: remove objects whose removal lowers Φ (argmin) -------------------------------
    keep = np.flatnonzero(alive[:n])
    indptr, nbr, ww = _csr(n, pi_all, pj_all, w_all)
    changed = True
    while changed:
        changed = False
        for k in keep[np.argsort(-energy[keep], kind="stable")]:
            if not alive[k]:
                continue
            inter = sum(ww[p] for p in range(indptr[k], indptr[k + 1]) if alive[nbr[p]])
            if energy[k] + params.gamma_overlap * inter >= 0.0:
                alive[k] = False
                changed = True
        keep = np.flatnonzero(alive[:n])
    # --- confidences (Gibbs distribution at β = 1) --------------------------------------------------
    conf = np.zeros(keep.size)
    for a, k in enumerate(keep):
        inter = sum(ww[p] for p in range(indptr[k], indptr[k + 1]) if alive[nbr[p]])
        conf[a] = 100.0 / (1.0 + math.exp(min(energy[k] + params.gamma_overlap * inter, 700.0)))
    xi_conf = np.full(keep.size, 100.0)
    if two and keep.size:
        raw = model.raw(rects[keep])
        alts = np.stack([model.data_energy(raw, np.full(keep.size, x, np.int8)) for x in (BOTH, ONLY_1, ONLY_2)])
        alts = alts[allowed] if allowed.size < 3 else alts
        pos = {x: i for i, x in enumerate(allowed if allowed.size < 3 else (BOTH, ONLY_1, ONLY_2))}
        ex = np.exp(-(alts - alts.min(axis=0)))
        mine = np.array([pos.get(int(x), 0) for x in xi[keep]])
        xi_conf = 100.0 * ex[mine, np.arange(keep.size)] / ex.sum(axis=0)
    inter_tot = 0.0
    if pi_all.size:
        both = alive[pi_all] & alive[pj_all]
        inter_tot = float(w_all[both].sum())
    energy_total = float(energy[keep].sum() + params.gamma_overlap * inter_tot)
    # --- L-shaped outlines: a corner notch cut from a kept object -------------------------------------
    out_rects, obj = rects[keep].copy(), np.arange(keep.size)
    object_id = None
    if params.edge_fit_carve and params.edge_fit == "joint" and with_dsm and keep.size:
        out_rects, obj = carve_notches(model, out_rects, xi[keep])
        n_cut = int(out_rects.shape[0] - keep.size)
        object_id = obj
        fit_notes.append(
            f"corner notch: {n_cut} of {keep.size} objects cut into an L (two rectangles; notch "
            "not raised and edged on every date the object exists on)"
        )
    return MPPResult(
        rects=out_rects,
        xi=xi[keep][obj].copy(),
        energy=energy[keep][obj].copy(),
        phi=phis[keep][obj].copy(),
        confidence=conf[obj],
        xi_confidence=xi_conf[obj],
        iterations=it,
        converged=converged,
        births=total_births,
        energy_total=energy_total,
        history=history,
        notes=fit_notes,
        object_id=object_id,
    )


def l_pieces(rect: np.ndarray, su: float, sv: float, a: float, b: float) -> np.ndarray:
    """The two rectangles of the L left when the corner notch of sides ``a`` (along e_L) × ``b`` (along e_l)
    at corner (``su``, ``sv``) (±1: the signs of u and v there) is cut from ``rect``.

    Of the two ways to cut an L into rectangles, the one whose narrower piece is wider: the full-length arm
    along the notch's shorter side.

    Returns
    -------
    float64 (2, 5): the full arm first, then the short one (they share one side; their union is the L)
    """
    cx, cy, eL, el, th = (float(x) for x in rect)
    c, s = math.cos(th), math.sin(th)
    if b >= a:  # arms: the whole e_L side × (e_l − b), and (e_L − a) × b
        pieces = [(0.0, -sv * 0.5 * b, eL, el - b), (-su * 0.5 * a, sv * 0.5 * (el - b), eL - a, b)]
    else:  # arms: (e_L − a) × the whole e_l side, and a × (e_l − b)
        pieces = [(-su * 0.5 * a, 0.0, eL - a, el), (su * 0.5 * (eL - a), -sv * 0.5 * b, a, el - b)]
    # (u, v) → (dx, dy): the inverse rotation of the kernels' u = dx c − dy s, v = dx s + dy c
    return np.array([(cx + c * u + s * v, cy - s * u + c * v, L, l, th) for u, v, L, l in pieces])


def carve_notches(model: EnergyModel, rects: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cut the best corner notch (:func:`_kernels.carve_corners`) from each rectangle that has one.

    Parameters
    ----------
    rects : float64 (n, 5); xi : int8 (n,)

    Returns
    -------
    rects : float64 (n', 5) — an uncut rectangle as it was, a cut one as the two rectangles of its L
        (:func:`l_pieces`), in the order of the input
    object_id : int64 (n',) — the input row each output rectangle comes from
    """
    feats = [t.features for t in model.terms]
    use = np.ones((rects.shape[0], len(feats)), bool)
    if len(feats) == 2:
        use[:, 0] = xi != ONLY_2
        use[:, 1] = xi != ONLY_1
    out = np.empty((rects.shape[0], 5))
    K.carve_corners(
        np.ascontiguousarray(rects, np.float64),
        use,
        np.stack([f.grad_mag for f in feats]).astype(np.float32),
        np.stack([f.grad_ori for f in feats]).astype(np.float32),
        np.stack([model._height_map(f) for f in feats]).astype(np.float32),
        np.stack([f.valid for f in feats]).astype(np.bool_),
        float(model.params.min_height_m),
        float(model.edge_w),
        float(model.smin),
        np.array([t.d_gradient for t in model.terms], np.float64),
        out,
    )
    rows, ids = [], []
    for r in range(rects.shape[0]):
        if out[r, 0] != 0.0:
            rows.append(l_pieces(rects[r], out[r, 0], out[r, 1], out[r, 2], out[r, 3]))
            ids += [r, r]
        else:
            rows.append(rects[r][None, :])
            ids.append(r)
    if not rows:
        return rects.copy(), np.zeros(0, np.int64)
    return np.concatenate(rows), np.array(ids, np.int64)


def fit_edges(
    model: EnergyModel, rects: np.ndarray, xi: np.ndarray, energy: np.ndarray, params: MPPParams
) -> dict[str, np.ndarray]:
    """Sub-cell placement of rectangles on the walls: first the sides are moved (see ``MPPParams.edge_fit``
    and :func:`_kernels.fit_sides`), then, with ``MPPParams.edge_fit_grow`` and DSMs, each rectangle's sides
    are pushed out over the raised block it stands on (:func:`_kernels.grow_sides`) and fitted again onto the
    walls, then each rectangle is turned to the angle of the strongest edge evidence within 3 σ_θ of its own
    (:func:`fit_rotation`, with ``MPPParams.edge_fit_rotate``). The side fit and the turn are kept when the
    gradient energy (the image's evidence of edges along the outline) does not rise on any date the object
    exists on and the object stays attractive (A_D < 0); a turn also needs A_D not to rise; a growth needs
    the object to stay attractive (a side moved from a roof's ridge to its wall may lose edge strength).
    ``energy`` is only used for the ``energy_not_worse`` count (A_D not raised), which docs/mpp.md reports.
    (Turning first, then moving the sides, gained less: +0.001 DP against +0.006 on sample_aoi seed 0.)

    Parameters
    ----------
    rects : float64 (n, 5); xi : int8 (n,); energy : float64 (n,) — their current A_D

    Returns
    -------
    dict with ``rects`` (what was kept: turned and/or refitted where ``accepted``, else as given), ``proposed``
    (the side refits proposed, kept or not), ``energy``, ``phi``, ``area`` (of ``rects``) and ``accepted``,
    ``grown`` (the growth was kept), ``turned`` (the turn was kept), ``moved`` (a turn, a refit or a growth
    was proposed) and ``energy_not_worse`` (bool (n,))
    """
    feats = [t.features for t in model.terms]
    two = len(feats) == 2
    use = np.ones((rects.shape[0], len(feats)), bool)
    if two:
        use[:, 0] = xi != ONLY_2
        use[:, 1] = xi != ONLY_1
    has_dsm = params.edge_fit == "joint" and all(f.ndsm is not None for f in feats)
    mags = np.stack([f.grad_mag for f in feats]).astype(np.float32)
    oris = np.stack([f.grad_ori for f in feats]).astype(np.float32)
    ndsms = (
        np.stack([f.ndsm for f in feats]).astype(np.float32) if has_dsm else np.zeros((len(feats), 1, 1), np.float32)
    )
    base = np.ascontiguousarray(rects, np.float64).copy()
    raw0 = model.raw(base)

    def keep(cand, raw_c, raw_ref):
        # the image's edge evidence must not weaken on any date the object exists on, and the object must
        # stay attractive (A_D < 0). A_D itself is not compared: its height ring ("the ring outside is
        # ground") is cleaner around a rectangle grown onto the stereo DSM's fattened walls, so it rewards
        # the offset this step corrects (docs/mpp.md, "Where the walls are")
        ok = np.any(cand != base, axis=1) & (model.data_energy(raw_c, xi) < 0.0)
        for k in range(len(model.terms)):
            g_new = model.feature_energy(k, raw_c[f"img{k}"])["gradient"]
            g_old = model.feature_energy(k, raw_ref[f"img{k}"])["gradient"]
            ok &= ~use[:, k] | (g_new <= g_old + 1e-12)
        return ok

    def pick(sel, raw_a, raw_b):  # rows of raw_a where sel, of raw_b elsewhere (features are per rectangle)
        return {k: np.where(sel.reshape((-1,) + (1,) * (v.ndim - 1)), v, raw_b[k]) for k, v in raw_a.items()}

    proposed = base.copy()
    K.fit_sides(
        proposed,
        use,
        mags,
        oris,
        ndsms,
        has_dsm,
        float(params.min_height_m),
        float(model.ring_w),
        0.25,
        float(model.edge_w),
        float(model.edge_w + model.ring_w),
        float(model.smin),
        float(model.smax),
    )
    raw_p = model.raw(proposed)
    sides = keep(proposed, raw_p, raw0)
    base = np.where(sides[:, None], proposed, base)
    raw = pick(sides, raw_p, raw0)
    grown = np.zeros(base.shape[0], bool)
    if params.edge_fit_grow and has_dsm:
        # the sides pushed out over the raised block, then onto its walls by the side fit; kept when the
        # object stays attractive (the fractions of A_D cannot reward covering more of the roof)
        big = base.copy()
        grew = np.zeros(base.shape[0], bool)
        valley = np.array([f.step_min_m for f in feats], np.float64)  # 3 √2 σ_z: a significant step
        K.grow_sides(big, use, ndsms, float(params.min_height_m), float(model.smax), 0.5, valley, grew)
        g = np.flatnonzero(grew)
        if g.size:  # only the grown rectangles are refitted and scored again
            sub = np.ascontiguousarray(big[g])
            K.fit_sides(
                sub,
                np.ascontiguousarray(use[g]),
                mags,
                oris,
                ndsms,
                has_dsm,
                float(params.min_height_m),
                float(model.ring_w),
                0.25,
                float(model.edge_w),
                float(model.edge_w + model.ring_w),
                float(model.smin),
                float(model.smax),
            )
            raw_g = model.raw(sub)
            keep_g = model.data_energy(raw_g, xi[g]) < 0.0
            grown[g[keep_g]] = True
            base[g[keep_g]] = sub[keep_g]
            for key, v in raw.items():
                v[g[keep_g]] = raw_g[key][keep_g]
    turned = np.zeros(base.shape[0], bool)
    rot = base
    if params.edge_fit_rotate:
        rot = fit_rotation(model, base, use, math.radians(3.0 * params.sigma_theta_deg))
        raw_r = model.raw(rot)
        # a turn at a fixed size and centre is also judged by A_D: the blurred walls that bias A_D towards
        # larger rectangles (the side fit's reason not to compare it) favour no angle
        turned = keep(rot, raw_r, raw) & (model.data_energy(raw_r, xi) <= model.data_energy(raw, xi) + 1e-12)
        raw = pick(turned, raw_r, raw)
    new = np.where(turned[:, None], rot, base)
    e_new = model.data_energy(raw, xi)
    phi = np.column_stack([model.phi(k, raw[f"img{k}"]) for k in range(len(model.terms))])
    moved = np.any(proposed != rects, axis=1) | np.any(rot != rects, axis=1)
    accepted = turned | sides | grown
    return {
        "rects": new,
        "proposed": proposed,
        "energy": e_new,
        "phi": phi,
        "area": raw["img0"][:, K.F_AREA],
        "accepted": accepted,
        "turned": turned,
        "grown": grown,
        "moved": moved | grown,
        "energy_not_worse": moved & (e_new <= energy + 1e-12),
    }


def fit_rotation(model: EnergyModel, rects: np.ndarray, use: np.ndarray, max_turn: float = math.pi / 4) -> np.ndarray:
    """Each rectangle turned about its centre to the angle where the images' edge evidence along its outline is
    strongest: the gradient energy summed over the dates it exists on (``use``), searched within ±``max_turn``
    of its angle in steps that move the end of the largest side by a quarter cell (the sub-cell step of the
    side fit; ties go to the smallest turn). A rectangle is turned only where that energy falls. The
    annealing's angles come from a 10° orientation histogram and 5° birth noise; measured against the
    footprints of four generated towns they are off by a median 2–5° and up to 17° (docs/mpp.md).
    :func:`fit_edges` searches within 3 σ_θ of the birth noise (15°): over the whole period (±45°) large
    rectangles on Kahramanmaraş's blocks turned by up to 45° onto other edges.

    Parameters
    ----------
    rects : float64 (n, 5); use : bool (n, n_images); max_turn : radians, at most π/4 (the whole period)

    Returns
    -------
    float64 (n, 5): the turned rectangles (sides and centre unchanged)
    """
    out = np.array(rects, np.float64, copy=True)
    if out.shape[0] == 0:
        return out
    step = math.atan(0.25 / (0.5 * model.smax))
    k = np.arange(-int(min(max_turn, math.pi / 4) / step), int(min(max_turn, math.pi / 4) / step) + 1)
    deltas = step * k[np.argsort(np.abs(k), kind="stable")]  # 0 first: ties go to the smallest turn
    nd = deltas.size
    cand = np.repeat(out, nd, axis=0)
    cand[:, 4] += np.tile(deltas, out.shape[0])
    cand[:, 4] = (cand[:, 4] + np.pi / 2) % np.pi - np.pi / 2
    raw = model.raw(cand)
    g = np.zeros(cand.shape[0])
    for k in range(len(model.terms)):
        g += np.where(np.repeat(use[:, k], nd), model.feature_energy(k, raw[f"img{k}"])["gradient"], 0.0)
    g = g.reshape(out.shape[0], nd)
    best = np.argmin(g, axis=1)
    turn = g[np.arange(out.shape[0]), best] < g[:, 0] - 1e-12
    out[turn, 4] = cand.reshape(out.shape[0], nd, 5)[turn, best[turn], 4]
    return out


def sd_combine(
    r1: MPPResult, r2: MPPResult, shape: tuple[int, int], min_cover: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """Sequential detection (SD, the paper's baseline): buildings found on each image alone, then compared.

    A date-1 rectangle covered at least ``min_cover`` by date-2 rectangles is unchanged (ξ = *), else
    demolished; a date-2 rectangle not so covered by date-1 rectangles is new (covered ones are the same
    buildings, already kept). Returns (rects, xi).
    """

    def union(rects):
        m = np.zeros(shape, bool)
        for r in rects:
            sl, u, v, _ = K._rect_grid(r, shape, 1.0)
            m[sl] |= (np.abs(u) <= r[2] / 2) & (np.abs(v) <= r[3] / 2)
        return m

    def cover(r, m):
        sl, u, v, _ = K._rect_grid(r, shape, 1.0)
        inside = (np.abs(u) <= r[2] / 2) & (np.abs(v) <= r[3] / 2)
        return float(m[sl][inside].mean()) if inside.any() else 0.0

    m1, m2 = union(r1.rects), union(r2.rects)
    xi1 = np.array([BOTH if cover(r, m2) >= min_cover else ONLY_1 for r in r1.rects], np.int8)
    keep2 = np.array([cover(r, m1) < min_cover for r in r2.rects], bool)
    rects = np.concatenate([r1.rects, r2.rects[keep2]]) if len(r2) else r1.rects
    xi = np.concatenate([xi1, np.full(int(keep2.sum()), ONLY_2, np.int8)])
    return rects, xi
