"""Shared machinery of both variants: views, pairs, stack layout, the two-pass tile driver.

Both variants produce, for every tile of reference pixels (key-frame pixels or
AOI-grid cells) and every hypothesis d, a *stack* of every image's bands
resampled onto the reference pixels; :func:`pair_volumes` turns it into patch
dissimilarities of the within-epoch pairs, and :func:`run_tiles` does

1. a sampling pass over tiles spread across the area (at most
   ``params.sigma_sample_px`` pixels) to estimate σ, σ' and S (§5.3.5) unless all
   are given, keeping those tiles' volumes when they fit a memory budget;
2. the main pass: volumes → :func:`~geocd.probchange.likelihood.evaluate_tile`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ..camera import Camera
from ..errors import ConfigError
from ..progress import Progress, ensure_progress
from ..stereo.sweep import ImageChip, Tile, prepare_chip
from . import _kernels as K
from .likelihood import (
    NoiseModel,
    TileEvidence,
    TileResult,
    estimate_noise_model,
    evaluate_tile,
    pair_minima,
    subsample,
)
from .params import ProbChangeParams

#: bytes of sampling-pass volumes kept for the main pass (recomputed beyond that)
CACHE_BUDGET_BYTES = 384 * 2**20


@dataclass(frozen=True)
class View:
    """One image of an epoch: its normalized band chips and its camera.

    Attributes
    ----------
    name : str
    chips : tuple of ImageChip — one per band (or one gray chip), all on the same pixel window
    camera : Camera (any kind)
    """

    name: str
    chips: tuple[ImageChip, ...]
    camera: Camera

    @property
    def n_bands(self) -> int:
        return len(self.chips)


def make_view(
    data: np.ndarray,
    camera: Camera,
    *,
    valid: np.ndarray | None = None,
    name: str = "",
    col0: int = 0,
    row0: int = 0,
    bands: str = "all",
    block_px: int = 256,
) -> View:
    """A :class:`View` from raw image data (any dtype: 8-bit, 11-bit in uint16, float; 1 or more bands).

    Each band is locally normalized to 0–255 (:func:`geocd.stereo.prepare_chip`);
    with ``bands="gray"`` the bands are averaged first.

    Parameters
    ----------
    data : (rows, cols) or (bands, rows, cols)
    col0, row0 : position of ``data[..., 0, 0]`` in the full image the camera describes
    """
    a = np.asarray(data)
    if a.ndim == 3 and a.shape[0] > 1 and bands == "all":
        chips = tuple(
            prepare_chip(a[b], valid, col0=col0, row0=row0, name=f"{name}:b{b + 1}", block_px=block_px)
            for b in range(a.shape[0])
        )
    else:
        chips = (prepare_chip(a, valid, col0=col0, row0=row0, name=name, block_px=block_px),)
    return View(name, chips, camera)


def as_gray(view: View) -> View:
    """The view with one chip: the mean of its band chips (for epochs mixing band counts)."""
    if view.n_bands == 1:
        return view
    data = np.mean(np.stack([c.data for c in view.chips]), axis=0).astype(np.float32)
    c0 = view.chips[0]
    return View(
        view.name,
        (ImageChip(np.ascontiguousarray(data), c0.col0, c0.row0, view.name, c0.noise_sigma, c0.shift),),
        view.camera,
    )


def harmonize_bands(views: Sequence[View], bands: str) -> list[View]:
    """Within one epoch all views must have the same band count for eq. 5.1; else gray levels."""
    views = list(views)
    if bands == "gray" or len({v.n_bands for v in views}) > 1:
        return [as_gray(v) for v in views]
    return views


def robust_linear_fit(x: np.ndarray, y: np.ndarray, n_iter: int = 12) -> tuple[float, float, int]:
    """``y ≈ g·x + o`` by iteratively reweighted least squares with Tukey's biweight (c = 4.685 MAD).

    Returns (g, o, number of samples used); (1, 0, n) when fewer than 200 samples.
    """
    ok = np.isfinite(x) & np.isfinite(y)
    x = np.asarray(x, np.float64)[ok]
    y = np.asarray(y, np.float64)[ok]
    if x.size < 200:
        return 1.0, 0.0, int(x.size)
    g, o = 1.0, float(np.median(y - x))
    for _ in range(n_iter):
        r = y - (g * x + o)
        sc = 1.4826 * float(np.median(np.abs(r - np.median(r)))) + 1e-6
        w = np.clip(1.0 - (r / (4.685 * sc)) ** 2, 0.0, None) ** 2
        sw = np.sqrt(w)
        A = np.stack([x * sw, sw], axis=1)
        sol, *_ = np.linalg.lstsq(A, y * sw, rcond=None)
        g, o = float(sol[0]), float(sol[1])
    return g, o, int(x.size)


def align_views(views: Sequence[View], lon: np.ndarray, lat: np.ndarray, h: np.ndarray) -> tuple[list[View], list]:
    """Put every view of an epoch on the radiometric scale of the first (per band, gain and offset).

    Images of one epoch see the same scene under the same sun, but their
    normalized gray levels still differ by view-dependent haze, gain and content
    (percentile stretches of different footprints): measured on sample_aoi, up to
    8 gray levels of offset between two views of one epoch, which eq. 5.1 (plain
    absolute differences) reads as dissimilarity. Each view is sampled at the
    same ground points (on an approximate surface, e.g. the prior DEM) and fitted
    ``v ≈ g · ref + o`` robustly (Tukey IRLS: buildings, trees and occlusions are
    outliers); its chips become ``(v − o)/g``. A fit with g outside [0.5, 2]
    (nothing in common) leaves the view as it is.

    Returns
    -------
    views : the aligned views (the first unchanged)
    fits : [(view name, band, g, o, n samples)]
    """
    from dataclasses import replace

    views = list(views)
    if len(views) < 2:
        return views, []
    ref = views[0]
    samp = []
    for v in views:
        c, r = v.camera.project(lon, lat, h)
        samp.append([chip.warp(c, r) for chip in v.chips])
    fits = []
    out = [ref]
    for k, v in enumerate(views[1:], start=1):
        chips = []
        for b, chip in enumerate(v.chips):
            g, o, n = robust_linear_fit(samp[0][b], samp[k][b])
            if 0.5 <= g <= 2.0 and n >= 200:
                chips.append(replace(chip, data=np.ascontiguousarray((chip.data - o) / g, np.float32)))
            else:
                chips.append(chip)
                g, o = 1.0, 0.0
            fits.append((v.name, b, round(g, 4), round(o, 3), n))
        out.append(View(v.name, tuple(chips), v.camera))
    return out, fits


def make_pairs(n: int, mode: str) -> list[tuple[int, int]]:
    """Image pairs within an epoch of ``n`` images (index 0 is the reference)."""
    if n < 2:
        return []
    if mode == "star":
        return [(0, j) for j in range(1, n)]
    if mode == "consecutive":
        return [(j, j + 1) for j in range(n - 1)]
    if mode == "all":
        return list(itertools.combinations(range(n), 2))
    raise ConfigError(f"unknown pair mode {mode!r}")


def check_epochs(views_a: Sequence[View], views_b: Sequence[View], label_a: str = "A", label_b: str = "B") -> None:
    """Each epoch needs two images or more (patches are compared only within an epoch)."""
    for lab, vs in ((label_a, views_a), (label_b, views_b)):
        if len(vs) < 2:
            names = ", ".join(v.name for v in vs) or "none"
            raise ConfigError(
                f"epoch {lab!r} has {len(vs)} image(s) ({names}); probabilistic change detection compares patches "
                "only between images of the same epoch, so each epoch needs at least two images that overlap. Add an "
                "image of that epoch (or use DEM differencing, which accepts one DEM per epoch)"
            )
        names = [v.name for v in vs]
        if len(set(names)) != len(names):
            raise ConfigError(f"epoch {lab!r} lists the same image twice ({names}); give distinct images")


@dataclass(frozen=True)
class StackLayout:
    """Where each view's bands sit in a sweep stack, and the within-epoch pairs.

    Views are ordered epoch A first, then epoch B; ``band_index[v]`` holds the
    stack indices of view v's chips; pairs are (view, view) indices.
    """

    views: tuple[View, ...]
    band_index: tuple[np.ndarray, ...]
    pairs_a: tuple[tuple[int, int], ...]
    pairs_b: tuple[tuple[int, int], ...]
    n_a: int

    @classmethod
    def build(
        cls,
        views_a: Sequence[View],
        views_b: Sequence[View],
        pairs_a: Sequence[tuple[int, int]],
        pairs_b: Sequence[tuple[int, int]],
    ) -> "StackLayout":
        views = tuple(views_a) + tuple(views_b)
        idx, k = [], 0
        for v in views:
            idx.append(np.arange(k, k + v.n_bands, dtype=np.int64))
            k += v.n_bands
        na = len(views_a)
        return cls(views, tuple(idx), tuple(pairs_a), tuple((a + na, b + na) for a, b in pairs_b), na)

    @property
    def n_chips(self) -> int:
        return int(sum(v.n_bands for v in self.views))

    def chips(self) -> list[ImageChip]:
        return [c for v in self.views for c in v.chips]

    def chip_cameras(self) -> list[Camera]:
        return [v.camera for v in self.views for _ in v.chips]

    def pair_names(self) -> dict[str, list[str]]:
        nm = lambda p: f"{self.views[p[0]].name}~{self.views[p[1]].name}"  # noqa: E731
        return {"a": [nm(p) for p in self.pairs_a], "b": [nm(p) for p in self.pairs_b]}


class PairMAD:
    """Patch MAD of every within-epoch pair of a stack, into hypothesis slot d of two volumes."""

    def __init__(self, layout: StackLayout, params: ProbChangeParams, shape: tuple[int, int]):
        self.layout = layout
        self.r = params.radius
        self.min_count = params.min_count
        self.hs = np.empty(shape, np.float64)
        self.hc = np.empty(shape, np.int32)

    def __call__(self, stack: np.ndarray, d: int, vol_a: np.ndarray, vol_b: np.ndarray) -> None:
        L = self.layout
        for vol, pairs in ((vol_a, L.pairs_a), (vol_b, L.pairs_b)):
            for p, (i, j) in enumerate(pairs):
                K.patch_mad(
                    stack, L.band_index[i], L.band_index[j], self.r, self.min_count, vol[p, d], self.hs, self.hc
                )


def _sample_tiles(tiles: Sequence[Tile], max_px: int) -> list[Tile]:
    total = sum(t.core_cells for t in tiles)
    if total <= max_px:
        return list(tiles)
    n = max(1, int(max_px // max(1, max(t.core_cells for t in tiles))))
    idx = np.unique(np.linspace(0, len(tiles) - 1, n).round().astype(int))
    return [tiles[i] for i in idx]


def run_tiles(
    tiles: Sequence[Tile],
    volumes: Callable[[Tile], TileEvidence | None],
    store: Callable[[Tile, TileEvidence, TileResult], None],
    params: ProbChangeParams,
    progress: Progress | None = None,
    seed: int = 0,
    *,
    map_store: Callable[[Tile, TileEvidence], None] | None = None,
    between: Callable[[NoiseModel], None] | None = None,
    mask: Callable[[Tile, TileEvidence], TileEvidence] | None = None,
) -> tuple[NoiseModel, dict]:
    """Two-pass driver: estimate the noise model (and optionally map both epochs), then evaluate every tile.

    ``volumes(tile)`` returns the tile's :class:`TileEvidence` (None: nothing to do
    there); ``store(tile, evidence, result)`` keeps the core of the result.
    With ``map_store`` the first pass visits *every* tile and hands each tile's
    evidence to ``map_store`` (e.g. to keep the most probable heights for a
    visibility test), then ``between(noise)`` runs, and the main pass applies
    ``mask(tile, evidence)`` before evaluating. Volumes are kept between the
    passes within :data:`CACHE_BUDGET_BYTES`, recomputed beyond.

    Returns
    -------
    noise : NoiseModel
    diagnostics : dict with the samples of min_d s (``a_min``, ``b_min``) used for σ (for plots)
    """
    prog = ensure_progress(progress)
    tiles = list(tiles)
    need = params.sigma is None or params.sigma_prime is None or params.uniform_range is None
    cache: dict[int, TileEvidence] = {}
    diag: dict = {"a_min": np.empty(0), "b_min": np.empty(0)}
    sample = _sample_tiles(tiles, params.sigma_sample_px) if need else []
    sample_ids = {t.index for t in sample}
    first = tiles if map_store is not None else sample
    n_work = len(first) + len(tiles)
    done = 0
    rng = np.random.default_rng(seed)
    a_min, b_min, a_all, b_all = [], [], [], []
    used = 0
    for t in first:
        prog(done / n_work, f"{'mapping' if map_store is not None else 'noise model'}: tile {t.index + 1}/{t.count}")
        ev = volumes(t)
        done += 1
        if ev is None:
            continue
        if map_store is not None:
            map_store(t, ev)
        if t.index in sample_ids:
            core = (slice(None), *t.inner)
            a_min.append(pair_minima(ev.s_a)[core].ravel())
            b_min.append(pair_minima(ev.s_b)[core].ravel())
            a_all.append(subsample(ev.s_a[(slice(None), slice(None), *t.inner)], 200_000, rng))
            b_all.append(subsample(ev.s_b[(slice(None), slice(None), *t.inner)], 200_000, rng))
        nbytes = ev.s_a.nbytes + ev.s_b.nbytes
        if used + nbytes <= CACHE_BUDGET_BYTES:
            cache[t.index] = ev
            used += nbytes
    if need:
        noise = estimate_noise_model(a_min, b_min, a_all, b_all, params)
        diag = {
            "a_min": np.concatenate(a_min) if a_min else np.empty(0),
            "b_min": np.concatenate(b_min) if b_min else np.empty(0),
        }
    else:
        noise = NoiseModel(
            float(params.sigma),
            float(params.sigma_prime),
            float(params.uniform_range),
            float(params.uniform_range),
            "given",
        )
    if between is not None:
        between(noise)
    for t in tiles:
        prog(done / n_work, f"tile {t.index + 1}/{t.count}")
        ev = cache.pop(t.index, None)
        if ev is None:
            ev = volumes(t)
        done += 1
        if ev is None:
            continue
        if mask is not None:
            ev = mask(t, ev)
        store(t, ev, evaluate_tile(ev, noise, params))
    prog(1.0, "done")
    return noise, diag


def map_summary(ev: TileEvidence) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Most similar hypothesis of each epoch and its dissimilarity: (k_a, k_b, s_a, s_b), (h, w) each.

    ``k`` is the argmin over d of the pairs' mean s (−1 where none; the argmax of
    p(d) for any σ and π∅), ``s`` that mean at k (NaN where none).
    """
    import warnings

    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for vol in (ev.s_a, ev.s_b):
            m = np.nanmean(vol, axis=0)  # (n, h, w)
            ok = np.isfinite(m).any(axis=0)
            k = np.where(ok, np.argmin(np.where(np.isfinite(m), m, np.inf), axis=0), -1).astype(np.int32)
            smin = np.where(ok, np.nanmin(m, axis=0), np.nan).astype(np.float32)
            out.append((k, smin))
    return out[0][0], out[1][0], out[0][1], out[1][1]


def confident_surface(
    h: np.ndarray, s_min: np.ndarray, sigma: float, max_sigmas: float = 3.0, median_px: int = 3
) -> np.ndarray:
    """Most probable heights kept only where the match is good (mean s ≤ max_sigmas · σ), median-filtered.

    The visibility z-buffer uses these: a noisy or unmatched "most probable"
    height (low texture, depth edges) would hide its neighbours for nothing.
    """
    from scipy import ndimage

    ok = np.isfinite(h) & np.isfinite(s_min) & (s_min <= max_sigmas * sigma)
    if median_px > 1 and ok.any():
        fill = np.where(ok, h, np.nanmedian(h[ok]))
        hm = ndimage.median_filter(fill, size=median_px, mode="nearest")
        return np.where(ok, hm, np.nan)
    return np.where(ok, h, np.nan)


def occluded_in_view(
    camera: Camera, chip: ImageChip, lon: np.ndarray, lat: np.ndarray, h: np.ndarray, tol_m: float, dilate_px: int = 1
) -> np.ndarray:
    """Points (lon, lat, h) hidden in a view behind higher points of the same set (height z-buffer).

    Every point is projected into the view; each image pixel keeps the highest
    point landing on it (for any camera looking down, higher along a ray = nearer
    the sensor), the buffer is dilated by ``dilate_px`` pixels (so sparse
    sampling of a roof leaves no holes), and a point lower than its pixel's
    buffer by more than ``tol_m`` is occluded. NaN heights are never occluded
    and occlude nothing.

    Returns
    -------
    bool array of the shape of ``h``
    """
    from scipy import ndimage

    c, r = camera.project(lon, lat, h)
    ox, oy = chip.origin
    H, W = chip.shape
    col = np.ascontiguousarray((c - ox).ravel(), np.float64)
    row = np.ascontiguousarray((r - oy).ravel(), np.float64)
    z = np.ascontiguousarray(np.asarray(h, np.float64).ravel())
    buf = np.full((H, W), -np.inf)
    K.zbuffer_max(col, row, z, buf)
    if dilate_px > 0:
        buf = ndimage.maximum_filter(buf, size=2 * dilate_px + 1, mode="nearest")
    out = np.zeros(z.shape, bool)
    K.zbuffer_test(col, row, z, buf, float(tol_m), out)
    return out.reshape(np.shape(h))


class VisibilityMasks:
    """Which views cannot see the other epoch's most probable surface, per reference pixel.

    For the A → B test, a pair of epoch-B views can only confirm the depth epoch's
    surface point where both views see it: pairs with a view in which the point
    is hidden (z-buffer of the depth epoch's most probable surface, see
    :func:`occluded_in_view`) are dropped from the observations of that pixel
    (all its hypotheses). The thesis has no such mechanism (its §5.4.2 names
    occlusion as the main error source); ``params.visibility = False`` restores it.
    For the symmetric test the roles swap (epoch-A views against B's surface).
    """

    def __init__(self, layout: StackLayout, params: ProbChangeParams, never: Sequence[int] = ()):
        self.layout = layout
        self.params = params
        self.never = set(never)
        self.occ: dict[int, np.ndarray] = {}

    def compute(
        self,
        surf_a: tuple[np.ndarray, np.ndarray, np.ndarray],
        surf_b: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> None:
        """``surf_x = (lon, lat, h)`` of each epoch's most probable surface at every reference pixel.

        Heights NaN where the surface is not trusted (:func:`confident_surface`): such
        points neither occlude nor are tested.
        """
        L = self.layout
        tol = float(self.params.visibility_tol_m)
        for v in range(L.n_a, len(L.views)):
            view = L.views[v]
            self.occ[v] = occluded_in_view(view.camera, view.chips[0], *surf_a, tol)
        if surf_b is not None:
            for v in range(L.n_a):
                if v in self.never:
                    continue
                view = L.views[v]
                self.occ[v] = occluded_in_view(view.camera, view.chips[0], *surf_b, tol)

    def fraction_hidden(self) -> dict[str, float]:
        return {self.layout.views[v].name: round(float(np.mean(o)), 4) for v, o in self.occ.items()}

    def apply(self, ev: TileEvidence, window: tuple[slice, slice]) -> TileEvidence:
        """Evidence whose observation volumes (``s_b_obs``, ``s_a_obs``) drop hidden pairs per pixel."""
        from dataclasses import replace

        def masked(vol: np.ndarray, pairs) -> np.ndarray | None:
            out = None
            for q, (i, j) in enumerate(pairs):
                m = None
                for v in (i, j):
                    if v in self.occ:
                        o = self.occ[v][window]
                        m = o if m is None else (m | o)
                if m is not None and m.any():
                    if out is None:
                        out = vol.copy()
                    out[q][:, m] = np.nan
            return out

        sb = masked(ev.s_b, self.layout.pairs_b)
        sa = masked(ev.s_a, self.layout.pairs_a)
        return replace(ev, s_b_obs=sb, s_a_obs=sa)
