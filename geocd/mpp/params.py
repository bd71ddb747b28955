"""Parameters of the multitemporal marked point process (building extraction + change).

Where each default comes from (none was chosen on a scene's truth):

* **Sizes** (metres, converted with the grid posting): rectangle sides 6–30 m — a large garage to the wing of
  a large building (bigger buildings are unions of rectangles, as in the paper); the orientation window
  ``l`` "just covers an average building" (paper §3.1): the mean of the side bounds.
* **Data thresholds** are measured on the images, not set: the gradient term's ``d_Λ`` is a quantile of
  the edge feature over random rectangles of the same image (a building outlines better than most random
  rectangles do), its scale ``D_Λ`` the spread of the upper tail; the texture-change threshold ``b0`` is
  Otsu's split of the Bhattacharyya distance over the cells both images see; the flood-fill tolerance is
  3 σ of the image noise.
* **Fractions** (colour, shadow, height fills, flood-fill completeness) are attractive above one half
  (a majority), and the kurtosis threshold 2.5 separates one mode (Gaussian: 3) from a half-roof that
  spills over a contrasted border (two modes: ≤ 2.5 for modes ≥ 1 σ apart).
* **Roof planarity** (with the height term): the tolerance is the noise of a 3 × 3 plane fit measured on
  each DSM's ground cells (median + 3 robust σ), as the flood-fill tolerance is 3 σ of the image noise;
  the largest rectangle side is raised to the 0.9 quantile of the DSM's raised segments' long sides.
* **Model weights**: ``gamma_overlap`` makes a duplicate of the best possible object (A_D = −2,
  IoU = 1) repulsive; ``gamma_change`` weighs the texture-change term like one image term.
* **Annealing**: the paper's geometric schedules (β up, δ down) with its convergence test and a cap.

``docs/mpp.md`` says on which scenes the few free choices were checked (other generated towns, LEVIR-CD
pairs) and which figures were measured on scenes used for choosing.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import ConfigError
from ..params import ParamsMixin

#: object-level features an image term can use
FEATURES = ("gradient", "homogeneity", "colour", "shadow", "height", "planarity", "step")


@dataclass(frozen=True)
class MPPParams(ParamsMixin):
    """How to detect buildings and their changes (see the module docstring for the defaults).

    Attributes
    ----------
    side_min_m, side_max_m : rectangle side bounds (m)
    side_max_from_dsm : with DSMs, raise ``side_max_m`` to the 0.9 quantile of the long sides of the scene's
        raised segments (dense city blocks larger than 30 m; see ``features.side_max_from_dsm``)
    window_m : orientation-statistics window l (m); None = mean of the side bounds
    orient_bins : orientation bins over 180°
    orient_kernel_deg : uniform kernel half-width of the orientation density (h)
    mode_spread_deg : spread d_λ of the bimodal Gaussian mixture
    sigma_theta_deg : σ_θ of a newborn's orientation around the dominant one
    edge_width_m : half-width of the dilated edge band of a rectangle
    ring_m : width of the outer ring T_u (colour, height, flood-fill neighbourhoods)
    shadow_ring_m : width of the shadow ring on the anti-sun side
    edge_mode : "mean" (the paper: Λ = mean over the whole edge band) or "sides" (the weakest of the four
        sides' means: a building is outlined on every side, a road segment on two)
    gradient_quantile : d_Λ = this quantile of Λ over random rectangles
    kurtosis_threshold : d_κ
    flood_spread : flood-fill tolerance of a roof half = max(3 σ_noise, flood_spread × the half's std)
    min_height_m : a building is raised at least this much above the ground (height term)
    prototypes : "auto" or features joined by "+" (AND: max of energies) and "|" (OR: min), e.g.
        "gradient+shadow|colour"; "auto" = gradient+homogeneity for grey images, gradient+shadow|colour for
        colour images (the paper's Budapest model)
    height : "off" (the paper) or "and" (beyond the paper, needs DSMs: the height term is required and any
        image cue confirms it — each image prototype, the gradient alone or the homogeneity alone, AND height)
    planarity : beyond the paper, with the height term: a roof is planar, a tree crown is rough at the cell
        scale (the tolerance, the noise of a 3 × 3 plane fit, is measured on the DSM's ground cells).
        "core": over half the cells of the rectangle's core (clear of the walls) must be planar; "roof": rough
        cells do not count as raised in the height term (a building is a raised planar block); "both"
        (default); "off": the height term alone
    step : beyond the paper, with the height term: a building is a raised block with steep edges. Each side
        is cut into segments of ``ring_m``; a segment steps when the mean height of the band just inside
        (``edge_width_m`` to ``edge_width_m + ring_m`` from the side) exceeds that of the band just outside
        by 3 √2 σ_z (σ_z: the DSM's noise, measured on its ground cells), and over half the segments must
        step. The step is relative to the neighbours, not to the ground: a block beside a taller or lower
        one steps too. "and": one more feature of every height prototype; "ring": it replaces
        "the ring outside is ground" in the height term, as an alternative (ground ring OR step), for dense
        blocks whose neighbours are raised; "off" (default: no gain on generated towns, a loss of buildings
        on real stereo DSMs, docs/mpp.md): no step term
    gamma_overlap : γ of the overlap interaction
    gamma_change : γ_ξ of the change term (the texture's, or the DSMs' with ``change_evidence``)
    change_evidence : beyond the paper, with the height term: what the ξ term reads as changed or
        unchanged under a rectangle. "texture": the paper's Bhattacharyya similarity of the two dates'
        gradient-orientation densities (Otsu's threshold); "height": the two DSMs, a cell changed when it
        stands more than ``min_height_m`` above the ground on one date only (a building that appeared or
        went; a tree crown stands on both dates; cells without DSM data keep the texture's verdict); "both":
        the mean of the two. Without DSMs the texture is used. The texture misreads both ways on geocd's
        data: unchanged roofs under another sun and view read as changed (tree crowns labelled new,
        unchanged buildings found on one date only), and a collapsed block whose cleared plot keeps the
        street grid's orientations reads as unchanged (docs/mpp.md)
    gamma_3d : weight of the 3-D change prior on ξ (0 = off)
    births_per_area : expected births per typical building area per step at δ = 1
    perturb_births : beyond the paper: each step, every live object also gives birth (probability δ) to a
        slightly perturbed copy of itself (±1 cell, ±2 cells of side, ±3°) that competes with it in the death
        step — local refinement inside multiple birth and death
    snap_births : beyond the paper: this share of the births has its sides moved onto the nearest strong edges
        (top decile of the gradient magnitude) seen from its centre along its axes — or, with the height
        term, onto the half-height crossings of the height map around a raised centre, each side then moved
        onto the strongest image edge within ``ring_m``; 0 = the paper's uniform sides
    edge_fit : beyond the paper: after the annealing, each side of each kept rectangle is moved along its
        normal in ¼-cell steps within ±``ring_m`` (the width of a stereo DSM's blurred walls) to where the
        image gradient across it is strongest, sampled bilinearly. "joint": only where the DSM agrees there
        is a wall there (``edge_width_m`` inside the side above half the rectangle's height, ``edge_width_m +
        ring_m`` outside below it, on over half the side; nothing is fitted without DSMs, so the paper's
        model is unchanged; default: +0.016 to +0.026 DP on the three towns it was not developed on);
        "image": the image edge alone; "off": none.
        A refit is kept when its gradient energy does not rise on any date the object exists on and it
        stays attractive (A_D < 0); A_D itself is not compared, because its height ring rewards the stereo
        DSM's walls, which lie up to 1.3 m outside the true ones (the ortho's edges: within 0.2 m; docs/mpp.md)
    edge_fit_rotate : beyond the paper, with ``edge_fit``: after the sides, each kept rectangle is turned
        about its centre to the angle (within 3 ``sigma_theta_deg`` of its own, the births' angle noise, in
        steps that move the end of the largest side by ¼ cell) where its gradient energy over the dates it
        exists on is lowest. The turn is kept by the side refit's rule and when A_D does not rise (the DSM's
        blurred walls, which bias A_D towards larger rectangles, favour no angle). The annealing's angles
        were off by a median 2–5°, up to 17°, on four generated towns; without the A_D rule and the 3 σ
        bound, large rectangles on Kahramanmaraş's blocks turned by up to 45° onto other edges (docs/mpp.md)
    edge_fit_grow : beyond the paper, with ``edge_fit="joint"`` and DSMs: after the side fit, each kept
        rectangle's sides are pushed outward over the raised surface it stands on — cell by cell, while the
        majority of the strip just beyond a side (its middle 80 %) stands above half the rectangle's median
        height on every date the object exists on, not into another rectangle, up to the largest side, and
        not out of a valley (the strip's median rising by more than 3 √2 σ_z, the step term's threshold,
        above the lowest strip crossed, itself that far below the rectangle's median: a second building
        across a gap the DSM blurs over) — and the side fit then puts the grown sides on the image's walls.
        The grown rectangle is kept when it stays attractive (A_D < 0). The data energy is made of
        fractions (raised, planar, edge strength per cell of outline), which a rectangle on one facet of a
        gabled roof satisfies as well as or better than the whole roof, whose shaded facet the stereo DSM
        reads lower and rougher: on four generated towns the energy preferred the found, too small rectangle
        for 20–25 of 25–30 buildings (docs/mpp.md). The growth reads the DSM's raised block instead. A_D is
        not compared, as for the side fit
    edge_fit_carve : beyond the paper, with ``edge_fit="joint"`` and DSMs: after the clean-up, a corner
        notch is cut from a kept rectangle when its cells are not raised (under half of them above
        ``min_height_m`` on the height term's map, its Q midpoint) and its two inner sides are edges (their
        mean gradient across them above the gradient term's d, the Q midpoint) on every date the object exists
        on; the notch keeps at least ``side_min_m`` of the rectangle on each axis, and each of its sides is at
        least two edge bands (2 ``edge_width_m``). The rectangle is then written as the two rectangles of an L,
        with the object's energies and confidences (``MPPResult.object_id``). A rectangle's fractions let one
        rectangle cover an L-shaped building whose inner corner the stereo DSM fills with its blurred walls;
        the notch reads the image's edges there (docs/mpp.md, "L-shaped buildings")
    wall_blur : beyond the paper, with the height term: how it reads a stereo DSM's blurred walls, whose
        extent is measured on each image without truth (``features.wall_blur_m``: the median nDSM profile
        across the image's strong edges where the DSM has a wall rises from 10 % of the wall's height
        ``wall_out_m`` outside the edge to 90 % ``wall_in_m`` inside; 1.9 m and 1.3 m on sample_aoi's date A).
        "off": the plain term (a ring cell, ``edge_width_m`` to ``edge_width_m + ring_m`` outside, is ground
        below ``min_height_m``; every inside cell counts for the raised fraction). "measured": a ring cell
        within ``wall_out_m`` of the rectangle is ground below half the rectangle's height (the half-height
        level of the height births: a true wall's blurred lower half, not a roof going on), and the raised
        fraction inside is counted past ``wall_in_m`` from the sides (the blurred wall's upper part is low or
        rough, and rough cells do not count as raised). A stereo DSM's walls spill 0.3–1.3 m outside the true
        ones, so the plain ring holds raised cells around a rectangle on the true walls and prefers one grown
        onto the DSM's walls (docs/mpp.md, "Where the walls are")
    absence : beyond the paper, with the height term: a change label (ξ = 1 demolished, ξ = 2 new) says the
        object is absent on the other date, and that date's DSM must not contradict it. "height": with r the
        share of the rectangle's cells standing more than ``min_height_m`` above the ground on the other date
        (rough cells too: a tree crown stands there as much as a roof does), A_D rises by max(0, 2 r − 1),
        the repulsive branch of Q(1 − r, ½, ¼) — the ground must make up at least half the object, as the
        raised fraction must inside a building. Like the texture-change term it only penalises (never
        attracts), so a change the other date's DSM supports is scored as before. "off": the paper's ξ
        terms only
    beta0, beta_factor, delta0, delta_factor : annealing schedules
    max_iter, min_iter : iteration cap and floor
    seed : random seed (same seed, same inputs → same objects)
    joint : True = joint model (ED); False = each image alone (SD building blocks)
    """

    _kind = "mpp"

    side_min_m: float = 6.0
    side_max_m: float = 30.0
    side_max_from_dsm: bool = True
    window_m: float | None = None
    orient_bins: int = 36
    orient_kernel_deg: float = 10.0
    mode_spread_deg: float = 10.0
    sigma_theta_deg: float = 5.0
    edge_width_m: float = 1.0
    ring_m: float = 2.0
    shadow_ring_m: float = 3.0
    edge_mode: str = "mean"
    gradient_quantile: float = 0.9
    kurtosis_threshold: float = 2.5
    flood_spread: float = 2.0
    min_height_m: float = 2.5
    prototypes: str = "auto"
    height: str = "off"
    planarity: str = "both"
    step: str = "off"
    gamma_overlap: float = 2.5
    gamma_change: float = 1.0
    gamma_3d: float = 0.0
    change_evidence: str = "height"
    births_per_area: float = 10.0
    perturb_births: bool = True
    snap_births: float = 0.5
    edge_fit: str = "joint"
    edge_fit_rotate: bool = True
    edge_fit_grow: bool = True
    edge_fit_carve: bool = True
    wall_blur: str = "off"
    absence: str = "off"
    beta0: float = 10.0
    beta_factor: float = 1.08
    delta0: float = 1.0
    delta_factor: float = 0.98
    max_iter: int = 250
    min_iter: int = 80
    seed: int = 0
    joint: bool = True

    def __post_init__(self) -> None:
        if not (0 < self.side_min_m < self.side_max_m):
            raise ConfigError(f"need 0 < side_min_m < side_max_m, got {self.side_min_m}, {self.side_max_m}")
        if self.edge_mode not in ("mean", "sides"):
            raise ConfigError(f"edge_mode must be mean or sides, got {self.edge_mode!r}")
        if self.height not in ("off", "and"):
            raise ConfigError(f"height must be off or and, got {self.height!r}")
        if not (0.5 <= self.gradient_quantile < 1):
            raise ConfigError(f"gradient_quantile must be in [0.5, 1), got {self.gradient_quantile}")
        if not (0 < self.delta_factor <= 1 and self.beta_factor >= 1):
            raise ConfigError("annealing needs delta_factor in (0, 1] and beta_factor ≥ 1")
        if not 0 <= self.snap_births <= 1:
            raise ConfigError(f"snap_births must be in [0, 1], got {self.snap_births}")
        if self.planarity not in ("off", "core", "roof", "both"):
            raise ConfigError(f"planarity must be off, core, roof or both, got {self.planarity!r}")
        if self.step not in ("off", "and", "ring"):
            raise ConfigError(f"step must be off, and or ring, got {self.step!r}")
        if self.wall_blur not in ("off", "measured"):
            raise ConfigError(f"wall_blur must be off or measured, got {self.wall_blur!r}")
        if self.absence not in ("off", "height"):
            raise ConfigError(f"absence must be off or height, got {self.absence!r}")
        if self.change_evidence not in ("texture", "height", "both"):
            raise ConfigError(f"change_evidence must be texture, height or both, got {self.change_evidence!r}")
        if self.edge_fit not in ("off", "joint", "image"):
            raise ConfigError(f"edge_fit must be off, joint or image, got {self.edge_fit!r}")
        if self.max_iter < 1 or self.min_iter < 0:
            raise ConfigError("max_iter must be ≥ 1 and min_iter ≥ 0")
        if self.prototypes != "auto":
            parse_prototypes(self.prototypes)

    @property
    def window(self) -> float:
        return self.window_m if self.window_m is not None else 0.5 * (self.side_min_m + self.side_max_m)


def parse_prototypes(text: str) -> list[list[str]]:
    """ "gradient+shadow|colour" → [["gradient", "shadow"], ["colour"]]."""
    protos = []
    for part in text.split("|"):
        feats = [f.strip() for f in part.split("+") if f.strip()]
        if not feats:
            raise ConfigError(f"empty prototype in {text!r}")
        bad = [f for f in feats if f not in FEATURES]
        if bad:
            raise ConfigError(f"unknown features {bad} in prototypes {text!r}; known: {FEATURES}")
        protos.append(feats)
    return protos
