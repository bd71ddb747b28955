"""Tiered change detection: the 2-D screen first, the 3-D methods only on the tiles it flags (``geocd run --screen``).

1. The screen runs on the manifest's views projected on the terrain DEM (no stereo needed):
   :func:`geocd.screen.pipeline.run_screen_manifest` on the run's AOI grid, threshold from a
   within-epoch no-change pair.
2. The grid is cut into square tiles (``tile_cells``). A screen cell counts as changed above
   :func:`flag_threshold`: the lower of the no-change pair's and the screened pair's own 99 %
   quantiles (the no-change pair's views can be farther apart than the screened pair's, and its
   quantile then sits above much of the change). A tile is flagged when its changed area (regions of
   at least ``min_region_m2``) exceeds what that 1 % rate gives by chance, and so is every tile a
   flagged tile's changed region reaches into (:func:`flag_tiles_by_chance`).
3. Stereo runs on windows around the flagged tiles (:func:`plan_stereo`): the stereo's tiles are the
   screen's tiles grouped into squares wide enough to keep every coarse level of the coarse-to-fine
   search (:func:`geocd.stereo.tiled.stereo_window_needs`; a narrower window searches more heights per
   cell), a stereo tile is matched when it holds a flagged tile, neighbours of a tile row as one
   window with one margin (:func:`geocd.stereo.tiled.run_stereo_tiled` with a tile selection; the
   pair's whole-scene pointing correction and noise level come from the central window). When those
   windows would read the whole grid anyway, the whole grid is matched once, untiled, as the full run
   does. The cores of unmatched tiles are written as not matched (``flags`` 255, ``FLAGS_NOT_EXAMINED``).
4. The self-consistency change test and the products follow (:func:`geocd.pipeline.run_change`)
   with the examined mask (the matched cells): cells of unmatched tiles get the change-mask code
   :data:`geocd.consistency.NOT_EXAMINED` (−127, "not examined"), never 0 ("unchanged"), and
   buildings with unobserved cells there the class ``not examined``.

Whole-scene statistics: the relative orientation runs on the whole scene before the screen; the
pair's pointing correction and noise level come from the central window; a scene-class model
(``--model``) is whole-scene by construction; a model learned here uses the within-epoch
comparisons of the flagged tiles (a sample of the scene; its bins report their counts), and the
change test's vertical offsets are medians over the examined cells. A transfer calibration (a
scene-class model) is fitted on the examined cells the screen calls unchanged
(:func:`calibration_cells`), since the examined tiles were chosen for their change; on every cell when
the whole grid was matched.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, EmptyDataError
from ..progress import Progress, ensure_progress, sub_progress


@dataclasses.dataclass(frozen=True)
class Flagged:
    """Tiles the screen flagged (the 3-D stage runs on these tiles only)."""

    tile_cells: int
    tiles: np.ndarray  # bool (tile rows, tile cols)

    @property
    def tile_fraction(self) -> float:
        return float(self.tiles.mean()) if self.tiles.size else 0.0

    def examined(self, shape: tuple[int, int]) -> np.ndarray:
        """bool (rows, cols): the cells of the flagged tiles' cores."""
        t = self.tile_cells
        m = np.repeat(np.repeat(self.tiles, t, axis=0), t, axis=1)
        return np.ascontiguousarray(m[: shape[0], : shape[1]])

    def cell_fraction(self, shape: tuple[int, int]) -> float:
        return float(self.examined(shape).mean())


def tile_sums(values: np.ndarray, tile_cells: int) -> np.ndarray:
    """float (tile rows, tile cols): the sum of ``values`` (rows, cols) over each tile of ``tile_cells`` cells
    (the tiling layer's row-major tiles; the last row and column of tiles may be partial)."""
    H, W = values.shape
    T = int(tile_cells)
    nr, nc = -(-H // T), -(-W // T)
    pad = np.zeros((nr * T, nc * T), np.float64)
    pad[:H, :W] = values
    return pad.reshape(nr, T, nc, T).sum(axis=(1, 3))


def flag_tiles(changed: np.ndarray, tile_cells: int, min_cells: int = 1) -> Flagged:
    """Tiles (of ``tile_cells`` cells, the tiling layer's row-major tiles) holding ≥ ``min_cells`` changed cells."""
    return Flagged(tile_cells, tile_sums(np.asarray(changed, bool), tile_cells) >= max(int(min_cells), 1))


def flag_threshold(d_screened: np.ndarray, null, false_alarm_pct: float = 1.0) -> tuple[float, str, dict]:
    """The dissimilarity above which the tiered run counts a screen cell as changed, and its rule.

    Two bounds on the unchanged cells' ``100 − false_alarm_pct`` percentile, the lower one kept:

    * the **no-change pair's** percentile (``null``): the estimate when that pair's views are as far
      apart as the screened pair's, an upper bound when they are farther apart (buildings lean more
      differently in its two views, so its unchanged cells are more dissimilar);
    * the **screened pair's own** percentile: with a fraction π of the cells changed, the unchanged
      cells above it are at most ``false_alarm_pct / (1 − π)`` percent of them, whatever the change
      looks like — a bound that needs no other pair, and that rises above the noise (fewer flags)
      only when the change covers more than ``false_alarm_pct`` of the grid, where the no-change
      pair's bound takes over.

    Either way the unchanged cells above the threshold are at most about ``2 · false_alarm_pct``
    percent. No Otsu split follows (as it does for the screen's own change mask): the values it cuts
    are the coarse grid's halo around a change, which lies in the change's tile or a neighbour and
    flags nothing a tile needs. Returns ``(threshold, rule, details)``.
    """
    v = np.asarray(d_screened, np.float64)
    v = v[np.isfinite(v)]
    q = 1.0 - float(false_alarm_pct) / 100.0
    t_own = float(np.quantile(v, q)) if v.size >= 100 else float("inf")
    t_null = float(null.threshold(false_alarm_pct)) if null is not None else float("inf")
    if not np.isfinite(min(t_own, t_null)):
        raise EmptyDataError(
            "the tiered run's flag threshold needs a no-change pair or at least 100 valid screened "
            "values: give a second view in one epoch, or check that the views overlap the AOI"
        )
    t = min(t_own, t_null)
    which = "the screened pair's own" if t_own <= t_null else f"the no-change pair's ({null.source})"
    rule = (
        f"min of the no-change pair's and the screened pair's own {100 * q:g} % quantiles "
        f"({t_null:.3f}, {t_own:.3f}): {which}; unchanged cells above it ≤ about {2 * false_alarm_pct:g} %"
    )
    return (
        t,
        rule,
        {"null_quantile": round(t_null, 4), "own_quantile": round(t_own, 4), "false_alarm_pct": float(false_alarm_pct)},
    )


def chance_cells(n_units: np.ndarray, rate: float, tile_false_alarm: float) -> np.ndarray:
    """The count of flagged units a tile of ``n_units`` independent units exceeds by chance with probability at
    most ``tile_false_alarm`` when each unit is flagged with probability ``rate`` (binomial upper quantile)."""
    from scipy.stats import binom

    n = np.maximum(np.round(np.asarray(n_units, np.float64)), 0).astype(np.int64)
    return np.where(n > 0, binom.isf(tile_false_alarm, np.maximum(n, 1), rate), 0.0)


def flag_tiles_by_chance(
    changed: np.ndarray,
    valid: np.ndarray,
    tile_cells: int,
    unit_cells: int,
    rate: float,
    tile_false_alarm: float | None = None,
) -> tuple[Flagged, dict]:
    """Tiles whose changed area exceeds what chance gives, plus the tiles a flagged tile's changes reach into.

    ``changed`` marks the screen's cells above :func:`flag_threshold` (regions already filtered by
    size). Unchanged cells land above it with probability ``rate`` (its false-alarm level), in units of
    a screen cell (``unit_cells`` on a side: the feature's cell, across which d_g is one value), so a
    tile of n valid units holds a Binomial(n, rate) count of them when nothing changed; a tile is
    flagged when its changed area, in units, exceeds that count's upper ``tile_false_alarm`` quantile
    (default: ``rate``, the same level). A changed object straddling a tile edge is cut by it: every
    tile that a connected changed region of a flagged tile reaches into is flagged too.
    Returns the flags and how they were set.
    """
    from scipy import ndimage

    tfa = float(rate if tile_false_alarm is None else tile_false_alarm)
    H, W = changed.shape
    T = int(tile_cells)
    u = float(unit_cells) ** 2
    n_units = tile_sums(np.asarray(valid, bool), T) / u
    k = chance_cells(n_units, rate, tfa)
    area = tile_sums(np.asarray(changed, bool), T) / u
    tiles = area > k
    by_chance = int(tiles.sum())
    lab, n = ndimage.label(changed, structure=np.ones((3, 3), bool))
    if n and tiles.any():
        core = Flagged(T, tiles).examined((H, W))
        reach = np.zeros(n + 1, bool)
        reach[np.unique(lab[core & (lab > 0)])] = True
        reach[0] = False
        tiles = tiles | (tile_sums(reach[lab], T) > 0)
    info = {
        "rule": f"a tile is flagged when its changed area exceeds the upper {100 * tfa:g} % quantile of a "
        f"Binomial(n, {rate:g}) count of {unit_cells}-cell units (n = its valid units), or when a "
        "changed region of a flagged tile reaches into it",
        "units_per_full_tile": round(float(T * T / u), 1),
        "chance_units_full_tile": float(chance_cells(np.array([T * T / u]), rate, tfa)[0]),
        "tiles_by_chance_rule": by_chance,
        "tiles_added_by_reach": int(tiles.sum()) - by_chance,
    }
    return Flagged(T, tiles), info


@dataclasses.dataclass(frozen=True)
class StereoPlan:
    """How a tiered run's 3-D stage covers the flagged tiles (:func:`plan_stereo`)."""

    tile_cells: int  # side of the stereo's tiles (a multiple of the screen's)
    tiles: np.ndarray  # bool (tile rows, tile cols) of those tiles: the ones matched
    whole_grid: bool  # True: one untiled match of the whole grid (as the full run)
    read_cells: int  # cells the windows would read (margins included)
    grid_cells: int

    def examined(self, shape: tuple[int, int]) -> np.ndarray:
        if self.whole_grid:
            return np.ones(shape, bool)
        return Flagged(self.tile_cells, self.tiles).examined(shape)

    def to_dict(self) -> dict:
        return {
            "stereo_tile_cells": int(self.tile_cells),
            "stereo_tiles": int(self.tiles.sum()),
            "stereo_tiles_in_grid": int(self.tiles.size),
            "whole_grid": bool(self.whole_grid),
            "window_read_fraction": round(self.read_cells / max(self.grid_cells, 1), 4),
        }


def plan_stereo(flagged: Flagged, shape: tuple[int, int], min_window_cells: int, margin_cells: int) -> StereoPlan:
    """Windows for the 3-D stage of a tiered run, sized from the scene and the flagged tiles.

    A stereo window narrower than ``min_window_cells`` loses coarse levels of the coarse-to-fine search
    and searches more heights per cell (:func:`geocd.stereo.tiled.stereo_window_needs`), so the
    stereo tiles are the screen's tiles grouped into squares of at least that side; a stereo tile is
    matched when it holds a flagged screen tile, and neighbouring ones of a tile row as one window
    with one margin. When those windows would read at least the whole grid (margins included), the
    whole grid is matched once, untiled, exactly as the full run does: on a scene that small,
    windows cost more than they save.
    """
    H, W = shape
    t0 = int(flagged.tile_cells)
    T = t0 * max(1, -(-int(min_window_cells) // t0))
    tiles = flag_tiles(flagged.examined(shape), T).tiles
    o = min(int(margin_cells), T // 2)
    read = 0
    for i in range(tiles.shape[0]):
        j = 0
        while j < tiles.shape[1]:
            if not tiles[i, j]:
                j += 1
                continue
            j0 = j
            while j < tiles.shape[1] and tiles[i, j]:
                j += 1
            r0, r1 = max(0, i * T - o), min(H, (i + 1) * T + o)
            c0, c1 = max(0, j0 * T - o), min(W, j * T + o)
            read += (r1 - r0) * (c1 - c0)
    return StereoPlan(T, tiles, bool(tiles.any()) and read >= H * W, int(read), int(H * W))


def calibration_cells(
    dissimilarity: np.ndarray, level: float, changed: np.ndarray, examined: np.ndarray, buffer_cells: int
) -> np.ndarray:
    """bool (rows, cols): the examined cells the screen calls unchanged — where a tiered run fits its transfer calibration.

    The flagged tiles were flagged *because* they hold change, so their cells are enriched in it; a
    calibration fitted on all of them reads that change as disagreement (a larger scale, fewer
    detections). Kept: examined cells whose screen dissimilarity is at most ``level`` (the median of
    the no-change pair's values: cells at least as alike as a typical unchanged cell, which leaves out
    the many changes too weak for the screen's 99 % threshold), away from screen-changed cells by
    ``buffer_cells`` (one screen cell: its coarse grid's halo). Cells the screen could not compare
    (NaN) are left out.
    """
    from scipy import ndimage

    d = np.asarray(dissimilarity, np.float64)
    near = np.asarray(changed, bool)
    if buffer_cells > 0 and near.any():
        near = ndimage.binary_dilation(near, structure=np.ones((3, 3), bool), iterations=int(buffer_cells))
    with np.errstate(invalid="ignore"):
        alike = np.isfinite(d) & (d <= float(level))
    return np.asarray(examined, bool) & alike & ~near


def fit_calibration_on(epoch_a, epoch_b, model, params, cells: np.ndarray):
    """The change test's transfer calibration fitted on ``cells`` only, and the vertical offsets it was fitted with.

    Same law and fit as :func:`geocd.change_test` does on every observed cell
    (:func:`geocd.consistency.fit_pair_calibration`), restricted to a selection (a tiered run's
    screen-unchanged examined cells, :func:`calibration_cells`). Returns ``(calibration or None,
    offsets)``: None when ``params.calibration`` does not ask for one (a model learned on these data
    with ``auto``, or ``none``) or when the selection holds too few cells (the change test then
    fits on all its cells, as without a screen). Pass both to the change test.
    """
    from ..consistency import (
        _comparison_arrays,
        apply_offsets,
        fit_pair_calibration,
        model_learned_on,
        vertical_offsets,
    )
    from ..errors import ProcessingError

    recs = list(epoch_a) + list(epoch_b)
    offsets = vertical_offsets(recs, mode=params.align)
    aligned = apply_offsets(recs, offsets)
    mode = params.calibration
    if mode == "auto":
        mode = "none" if model_learned_on(model, aligned) else "pair"
    if mode != "pair":
        return None, offsets
    na = len(epoch_a)
    posting = getattr(getattr(aligned[0], "grid", None), "posting_m", None)
    sel = np.asarray(cells, bool)
    parts = [[], [], [], []]
    for p in aligned[:na]:
        for q in aligned[na:]:
            dt, sc, _, both, mpu, slope = _comparison_arrays(p, q, posting)
            keep = both & sel
            for lst, arr in zip(parts, (dt, sc, slope, mpu)):
                lst.append(np.asarray(arr)[keep])
    try:
        cal = fit_pair_calibration(model, *(np.concatenate(x) for x in parts), fit_edge=bool(posting))
    except ProcessingError:
        return None, offsets
    return cal, offsets


def run_stereo_screened(
    manifest,
    *,
    out: Path,
    stereo_params,
    screen_params,
    epochs: list[str],
    pairs: str,
    posting_m: float | None = None,
    epoch_a: str | None = None,
    epoch_b: str | None = None,
    tile_cells: int = 128,
    min_region_m2: float = 4.0,
    scheduler: str = "sync",
    stereo_plan: str = "auto",
    flag_rule: str = "chance",
    false_alarm_pct: float = 1.0,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """The screen, then geocd stereo on the flagged tiles only.

    ``flag_rule``: "chance" (a cell counts above :func:`flag_threshold`, the lower of the no-change pair's
    and the screened pair's own ``100 − false_alarm_pct`` percentiles; a tile is flagged when its
    changed area exceeds chance, :func:`flag_tiles_by_chance`) or "any" (the screen's change mask,
    whose threshold is the no-change pair's percentile then Otsu's split above it, and any changed
    region of ``min_region_m2`` flags its tile: the rule before, kept to measure against).

    ``stereo_plan``: "auto" (:func:`plan_stereo`: windows of the stereo's own size around the flagged
    tiles, or the whole grid untiled when those would read all of it) or "tiles" (each run of flagged
    screen tiles matched as its own window, with its margin — slower on small scenes, kept to measure
    against).

    Returns run_stereo's dict (``outputs``, ``grid``, ``pairs`` as PairDEMs on the whole grid) + ``examined``
    (bool (rows, cols), the cells the 3-D stage matched), ``calibration_cells`` (bool (rows, cols), the examined
    cells the screen calls unchanged, :func:`calibration_cells`; None when the whole grid was matched) and
    ``screen`` (flags, fractions, plan, seconds).
    """
    from scipy import ndimage

    from ..tiling.params import TilingParams
    from ..io.raster import read_dem
    from ..stereo import read_pair_dem
    from ..stereo.scene import default_aoi_grid, load_epoch_images
    from ..stereo.pipeline import run_stereo
    from ..stereo.tiled import run_stereo_tiled, stereo_window_needs
    from .pipeline import run_screen_manifest

    prog = ensure_progress(progress)
    m = manifest
    images = {e: load_epoch_images(m, m.epoch(e)) for e in epochs}
    dem_median = None
    if m.dem is not None:
        dem_median = float(
            np.nanmedian(read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m)
        )
    grid = default_aoi_grid(m, images, posting_m=posting_m, dem_median=dem_median, params=stereo_params)
    t0 = time.perf_counter()
    sc = run_screen_manifest(
        m,
        out=out / "screen",
        params=screen_params,
        grid=grid,
        epoch_a=epoch_a,
        epoch_b=epoch_b,
        progress=sub_progress(prog, 0.0, 0.2, "screen: "),
    )
    t_screen = time.perf_counter() - t0
    sr = sc["run"]
    null = sc.get("null")
    if flag_rule == "chance":
        t_flag, flag_rule_text, flag_info = flag_threshold(sr.dissimilarity, null, false_alarm_pct)
    elif flag_rule == "any":
        t_flag, flag_rule_text, flag_info = float(sc["threshold"]), "the screen's change mask (" + sc["rule"] + ")", {}
    else:
        raise ConfigError(f"flag_rule must be 'chance' or 'any', got {flag_rule!r}")
    changed = sr.valid & np.isfinite(sr.dissimilarity) & (sr.dissimilarity > t_flag)
    lab, n = ndimage.label(changed, structure=np.ones((3, 3), bool))
    if n:
        sizes = np.bincount(lab.ravel())
        keep = sizes >= max(1, int(np.ceil(min_region_m2 / grid.cell_area_m2)))
        keep[0] = False
        changed = keep[lab]
    if flag_rule == "chance":
        fl, tile_info = flag_tiles_by_chance(changed, sr.valid, tile_cells, sr.cell_px, false_alarm_pct / 100.0)
    else:
        fl = flag_tiles(changed, tile_cells)
        tile_info = {"rule": f"a tile is flagged when it holds a changed region of at least {min_region_m2:g} m²"}
    # where the transfer calibration is fitted: examined cells the screen calls unchanged
    level = float(np.median(null.values)) if null is not None else float(sc["threshold"])
    t1 = time.perf_counter()
    if stereo_plan == "auto":
        needs = [
            stereo_window_needs(m, grid, a, b, stereo_params)
            for e in epochs
            for a, b in itertools.combinations(images[e], 2)
            if pairs == "all" or a.camera.kind == b.camera.kind
        ]
        plan = plan_stereo(fl, grid.shape, max(n[1] for n in needs), max(n[0] for n in needs))
    else:  # the screen's own tiles, each matched with its margin
        plan = StereoPlan(tile_cells, fl.tiles, False, 0, int(np.prod(grid.shape)))
    if plan.whole_grid:
        st = run_stereo(
            m,
            epochs=epochs,
            out_dir=out,
            params=stereo_params,
            grid=grid,
            keep_arrays=True,
            pairs=pairs,
            orient=False,
            progress=sub_progress(prog, 0.2, 1.0, "stereo (whole grid): "),
        )
        st.setdefault("margins", {})
    else:
        tiling = TilingParams(tile_size=plan.tile_cells, scheduler=scheduler)
        st = run_stereo_tiled(
            m,
            out_dir=out,
            epochs=epochs,
            params=stereo_params,
            grid=grid,
            pairs=pairs,
            tiling=tiling,
            tiles=plan.tiles,
            progress=sub_progress(prog, 0.2, 1.0, "stereo on flagged tiles: "),
        )
    t_3d = time.perf_counter() - t1
    # the 3-D stage examined what it matched (the whole grid, or the stereo tiles holding flagged tiles)
    examined = plan.examined(grid.shape)
    # the calibration's bias comes from examining change-rich tiles only; the whole grid examined is no selection,
    # and the change test then fits on every cell as the full run does
    cal_cells = None if plan.whole_grid else calibration_cells(sr.dissimilarity, level, changed, examined, sr.cell_px)
    kept = st.get("pairs") or {key: read_pair_dem(p) for key, p in st["outputs"].items()}
    info = {
        "threshold": round(float(sc["threshold"]), 4),
        "rule": sc["rule"],
        "feature": screen_params.feature.label,
        "flag_threshold": round(float(t_flag), 4),
        "flag_rule": flag_rule_text,
        **flag_info,
        "tile_rule": tile_info,
        "pair": list(sc["pair"]),
        "tile_cells": tile_cells,
        "stereo_margin_cells": st["margins"],
        "flagged_tiles": int(fl.tiles.sum()),
        "tiles": int(fl.tiles.size),
        "flagged_tile_fraction": round(fl.tile_fraction, 4),
        "flagged": [[int(i), int(j)] for i, j in zip(*np.nonzero(fl.tiles))],
        "screen_flagged_cell_fraction": round(fl.cell_fraction(grid.shape), 4),
        "stereo_plan": plan.to_dict(),
        "stereo_cell_fraction": round(float(examined.mean()), 4),
        "calibration_cells": (
            "all (the whole grid was examined)"
            if cal_cells is None
            else {
                "fraction": round(float(cal_cells.mean()), 4),
                "dissimilarity_at_most": round(level, 4),
                "level": "no-change pair's median" if null is not None else "threshold",
                "buffer_cells": int(sr.cell_px),
            }
        ),
        "screen_seconds": round(t_screen, 2),
        "stereo_seconds": round(t_3d, 2),
    }
    prog(1.0, "screened stereo done")
    return {
        "outputs": st["outputs"],
        "grid": grid,
        "pairs": kept,
        "screen": info,
        "examined": examined,
        "calibration_cells": cal_cells,
        "screen_outputs": {f"screen:{k}": v for k, v in sc["outputs"].items() if not k.startswith("view:")},
    }
