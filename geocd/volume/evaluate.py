"""Evaluation of the volume model on a scene with truth (``geocd synth`` scenes such as sample_aoi).

Run::

    python -m geocd.volume.evaluate sample_aoi --out geocd_out/volume_eval

It trains the octree model on epoch A (all satellite and aerial views but one
held-out satellite view), then reports

* change detection on every epoch-B satellite image against its per-image truth
  mask (ROC/AUC with :mod:`geocd.change.metrics`), per pixel (the paper's eq. 27)
  and after the same 9×9 log-odds aggregation for every method, next to two 2-D
  baselines (DEM warp + difference, Carlotto's joint-histogram predictor), with
  false-alarm rates at building edges/occlusions and elsewhere;
* octree vs fixed grid at the same finest cell (storage on the full AOI, and
  storage + AUC of both trained on a central sub-area);
* the expected image of the held-out view (PSNR) and the expected height map
  against the truth DSM (median |Δz|).

Figures ``volume_*.png`` and ``volume_results.json`` go to ``--out`` (default
``./geocd_out/volume_eval``); the trained model goes to ``--work`` (default
``OUT/work``), as ``volume_octree``.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..change.metrics import roc_curve
from ..geodesy import AOIGrid
from ..io.manifest import load_manifest
from ..io.raster import read_dem, read_image
from . import (
    DetectParams,
    VolumeModel,
    VolumeParams,
    detect_change,
    expected_height_map,
    expected_image,
    save_model,
    update_model,
)
from .baseline import carlotto_score, difference_score, edge_zone, first_surface_height, nearest_view, warp_reference
from .detect import aggregate_log_odds
from .io import geometry_from_manifest, read_shadow_dsm, read_view
from .prior import DEMPrior, roof_surface, seed_from_dem
from .scene import geometry_for_aoi


@dataclass
class TrainConfig:
    passes: int = 5
    finest_cell_m: float = 0.5
    max_depth: int = 3
    init_depth: int = 1
    above_m: float = 30.0
    dem_prior: bool = True
    ground_band_m: float = 0.5
    ground_band_top_m: float = 0.0
    ground_p_max: float = 0.9
    footprints: bool = False
    seed: int = 0


def train(
    views: list,
    geom,
    grid: AOIGrid,
    dem_m: np.ndarray | None,
    cfg: TrainConfig,
    *,
    fixed_grid: bool = False,
    footprints: np.ndarray | None = None,
    log=print,
) -> tuple[VolumeModel, dict]:
    """Train a model on ``views`` (several passes in random order); returns it with timing figures."""
    params = VolumeParams(refine=not fixed_grid)
    model = VolumeModel.create(geom, params, init_depth=geom.max_depth if fixed_grid else cfg.init_depth)
    info: dict = {}
    if cfg.dem_prior and dem_m is not None:
        prior = DEMPrior(
            ground_band_m=cfg.ground_band_m, ground_band_top_m=cfg.ground_band_top_m, ground_p_max=cfg.ground_p_max
        )
        roof = None
        if cfg.footprints and footprints is not None and footprints.any():
            t0 = time.perf_counter()
            roof, ri = roof_surface(views, footprints, dem_m, grid, prior, step_m=geom.finest_cell_m)
            info = {"footprints": ri["footprints"], "roofs": ri["roofs"], "roof_sweep_s": time.perf_counter() - t0}
            log(
                f"  roofs from footprints: {ri['roofs']} of {ri['footprints']} footprints, {info['roof_sweep_s']:.0f} s"
            )
        seed_from_dem(model, dem_m, grid, prior, roof_m=roof)
    rng = np.random.default_rng(cfg.seed)
    t0 = time.perf_counter()
    segs = 0
    n_upd = 0
    rays: list[dict] = [{} for _ in views]  # each view's rays, computed on its first update
    for p in range(cfg.passes):
        for i in rng.permutation(len(views)):
            v = views[i]
            st = update_model(model, v.intensity, v.camera, sun=v.sun, name=v.name, ray_cache=rays[i])
            segs += st.segments
            n_upd += 1
        r = model.size_report()
        log(
            f"  pass {p + 1}/{cfg.passes}: {r['leaves']:,} leaves, {r['bytes'] / 2**20:.1f} MiB, "
            f"{time.perf_counter() - t0:.0f} s"
        )
    secs = time.perf_counter() - t0
    return model, {"train_s": secs, "updates": n_upd, "segments": int(segs), "segments_per_s": segs / secs, **info}


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    err = (a[mask] - b[mask]) ** 2
    return float(10 * np.log10(1.0 / np.mean(err)))


def _roc(score, truth, valid):
    fpr, tpr, thr, auc = roc_curve(score, truth, valid)
    return {"fpr": fpr, "tpr": tpr, "thr": thr, "auc": auc}


def fa_at_tpr(score: np.ndarray, truth: np.ndarray, valid: np.ndarray, zone: np.ndarray, tpr: float = 0.5) -> dict:
    """False-alarm rate inside and outside ``zone`` at the threshold reaching ``tpr`` on the changed pixels."""
    s = score[valid & truth]
    thr = float(np.quantile(s, 1.0 - tpr))
    neg = valid & ~truth
    fa_in = float(np.mean(score[neg & zone] >= thr)) if (neg & zone).any() else float("nan")
    fa_out = float(np.mean(score[neg & ~zone] >= thr)) if (neg & ~zone).any() else float("nan")
    return {
        "threshold": thr,
        "fa_edges": fa_in,
        "fa_elsewhere": fa_out,
        "edge_share_of_false_alarms": float(np.sum(score[neg & zone] >= thr) / max(np.sum(score[neg] >= thr), 1)),
    }


def evaluate(
    scene: str,
    out_dir: str,
    work_dir: str,
    *,
    holdout: str = "A_sat3",
    cfg: TrainConfig | None = None,
    subarea_m: float = 150.0,
    aggregate_px: int = 9,
    do_grid: bool = True,
    shadow_dsm_path: str | None = None,
    log=print,
) -> dict:
    """The docs/volume.md evaluation of one scene with truth (module doc). ``shadow_dsm_path``: a DSM of
    epoch A (e.g. ``geocd ortho``'s ``dsm_A.tif``) whose cast shadows the relit detections use."""
    cfg = cfg or TrainConfig()
    out = Path(out_dir)
    work = Path(work_dir)
    out.mkdir(parents=True, exist_ok=True)
    work.mkdir(parents=True, exist_ok=True)
    man = load_manifest(scene)
    geom, grid = geometry_from_manifest(
        man, finest_cell_m=cfg.finest_cell_m, max_depth=cfg.max_depth, above_m=cfg.above_m
    )
    dem = read_dem(man.dem.path, grid=grid, vertical_datum=man.dem.vertical_datum).to_ellipsoidal().height_m
    views_a = [read_view(s.path, s.camera, name=s.name) for s in man.epoch("A").images]
    views_b = [read_view(s.path, s.camera, name=s.name) for s in man.epoch("B").images if "sat" in s.name]
    train_views = [v for v in views_a if v.name != holdout]
    held = [v for v in views_a if v.name == holdout]
    res: dict[str, Any] = {
        "scene": str(scene),
        "config": cfg.__dict__,
        "holdout": holdout,
        "train_views": [v.name for v in train_views],
        "geometry": geom.to_dict(),
        "shadow_dsm": shadow_dsm_path,
    }
    shadow = read_shadow_dsm(shadow_dsm_path, grid) if shadow_dsm_path else None
    log(
        f"octree model: {geom.n_blocks} blocks of {geom.block_size_m} m, finest {geom.finest_cell_m} m; "
        f"training on {[v.name for v in train_views]}"
    )
    fp = footprint_mask(man, grid)
    model, tr = train(train_views, geom, grid, dem, cfg, footprints=fp, log=log)
    res["octree_training"] = tr
    res["octree_size"] = model.size_report()
    save_model(model, work / "volume_octree")
    from .io import disk_bytes

    res["octree_size"]["disk_bytes"] = disk_bytes(work / "volume_octree")

    # --- held-out view: expected image -------------------------------------------------------
    figs = {}
    if held:
        v = held[0]
        r = expected_image(model, v.camera, v.intensity.shape, sun=v.sun)
        known = np.isfinite(v.intensity) & (r.vis_inf <= 0.2)
        res["heldout"] = {
            "name": v.name,
            "psnr_db": psnr(r.expected, v.intensity, known),
            "known_fraction": float(known.mean()),
        }
        # the same for a training view, to separate fit from prediction
        vt = train_views[0]
        rt = expected_image(model, vt.camera, vt.intensity.shape, sun=vt.sun)
        kt = np.isfinite(vt.intensity) & (rt.vis_inf <= 0.2)
        res["training_view_psnr_db"] = {"name": vt.name, "psnr_db": psnr(rt.expected, vt.intensity, kt)}
        figs["expected"] = (v.intensity, r.expected, known)
        log(
            f"held-out {v.name}: PSNR {res['heldout']['psnr_db']:.2f} dB (training view {vt.name}: "
            f"{res['training_view_psnr_db']['psnr_db']:.2f} dB)"
        )

    # --- height map ----------------------------------------------------------------------------
    h, hg = expected_height_map(model, grid)
    dsm_a = read_dem(man.truth_path("dsm_A"), grid=grid).height_m
    dz = h - dsm_a
    ok = np.isfinite(dz)
    res["height_map"] = {
        "median_abs_dz_m": float(np.median(np.abs(dz[ok]))),
        "nmad_m": float(1.4826 * np.median(np.abs(dz[ok] - np.median(dz[ok])))),
        "within_1m": float(np.mean(np.abs(dz[ok]) < 1.0)),
        "bias_m": float(np.median(dz[ok])),
        "coverage": float(ok.mean()),
    }
    figs["height"] = (h, dsm_a)
    log(
        f"height map: median |dz| {res['height_map']['median_abs_dz_m']:.2f} m, "
        f"{100 * res['height_map']['within_1m']:.0f}% within 1 m"
    )

    # --- change detection on epoch B --------------------------------------------------------
    dsm_b = read_dem(man.truth_path("dsm_B"), grid=grid).height_m
    ref_pool = [v for v in views_a if "sat" in v.name and v.name != holdout]
    pooled: dict[str, list] = {}
    per_image = []
    for v in views_b:
        truth = read_image(man.root / man.truth["image_masks"][v.name]).data[0] > 0
        t0 = time.perf_counter()
        det = detect_change(
            model, v.intensity, v.camera, sun=v.sun, name=v.name, params=DetectParams(neighborhood=1), shadow_dsm=shadow
        )
        t_det = time.perf_counter() - t0
        det_plain = detect_change(
            model, v.intensity, v.camera, sun=v.sun, name=v.name, params=DetectParams(relight=False, neighborhood=1)
        )
        det_nxn = detect_change(
            model, v.intensity, v.camera, sun=v.sun, name=v.name, params=DetectParams(neighborhood=3), shadow_dsm=shadow
        )
        k = nearest_view(v.camera, v.intensity.shape, ref_pool, geom)
        ref = ref_pool[k]
        warped = warp_reference(v.camera, v.intensity.shape, ref.intensity, ref.camera, dem, grid)
        diff = difference_score(v.intensity, warped)
        carl = carlotto_score(v.intensity, warped)
        heights = first_surface_height(v.camera, v.intensity.shape, dsm_b, grid, geom)
        zone = edge_zone(heights)
        valid = ~det.unknown & np.isfinite(diff) & np.isfinite(carl)
        # scores (higher = change); 2-D scores turned into probabilities for the aggregation by rank
        scores = {
            "3-D octree (relit)": det.probability,
            "3-D octree (nearest sun bin)": det_plain.probability,
            "3-D octree 3×3 (relit)": det_nxn.probability,
            "2-D DEM warp + difference": diff,
            "2-D Carlotto joint histogram": carl,
        }
        entry = {
            "name": v.name,
            "reference_view": ref.name,
            "valid_fraction": float(valid.mean()),
            "changed_fraction": float(truth[valid].mean()),
            "edge_zone_fraction": float(zone[valid].mean()),
            "detect_s": t_det,
            "relight": det.relight,
            "methods": {},
        }
        for name, sc in scores.items():
            agg = aggregate_log_odds(_to_prob(sc, valid), aggregate_px)
            r1 = _roc(sc, truth, valid)
            r9 = _roc(agg, truth, valid)
            fa = fa_at_tpr(np.where(valid, sc, np.nan), truth, valid, zone)
            entry["methods"][name] = {"auc": r1["auc"], f"auc_agg{aggregate_px}": r9["auc"], "fa_at_tpr50": fa}
            pooled.setdefault(name, []).append((sc[valid], agg[valid], truth[valid], zone[valid]))
        per_image.append(entry)
        figs.setdefault("maps", (v, truth, det.probability, carl, zone, det.expected))
        log(
            f"{v.name}: AUC 3-D {entry['methods']['3-D octree (relit)']['auc']:.3f} "
            f"(agg {entry['methods']['3-D octree (relit)'][f'auc_agg{aggregate_px}']:.3f}), "
            f"Carlotto {entry['methods']['2-D Carlotto joint histogram']['auc']:.3f} "
            f"(agg {entry['methods']['2-D Carlotto joint histogram'][f'auc_agg{aggregate_px}']:.3f})"
        )
    res["change"] = per_image
    res["change_pooled"] = {}
    curves = {}
    for name, parts in pooled.items():
        s1 = np.concatenate([p[0] for p in parts])
        s9 = np.concatenate([p[1] for p in parts])
        t = np.concatenate([p[2] for p in parts])
        z = np.concatenate([p[3] for p in parts])
        allv = np.ones(t.size, bool)
        r1 = _roc(s1, t, allv)
        r9 = _roc(s9, t, allv)
        curves[name] = (r1, r9)
        res["change_pooled"][name] = {
            "auc": r1["auc"],
            f"auc_agg{aggregate_px}": r9["auc"],
            "fa_at_tpr50": fa_at_tpr(s1, t, allv, z),
            f"fa_at_tpr50_agg{aggregate_px}": fa_at_tpr(s9, t, allv, z),
        }

    # --- octree vs fixed grid ---------------------------------------------------------------------
    if do_grid:
        res["grid_vs_octree"] = _grid_comparison(man, grid, dem, train_views, views_b, cfg, subarea_m, work, log)
    _figures(out, figs, curves, res, aggregate_px)
    (out / "volume_results.json").write_text(json.dumps(res, indent=1, default=_json), encoding="utf-8")
    return res


def _to_prob(score: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """A score as a probability-like value in (0, 1) by its rank among valid pixels (for the aggregation)."""
    s = np.asarray(score, dtype=np.float64)
    if np.nanmin(s[valid]) >= 0 and np.nanmax(s[valid]) <= 1:
        out = s.copy()
    else:
        v = s[valid]
        srt = np.sort(v)
        out = np.full(s.shape, np.nan)
        out[valid] = (np.searchsorted(srt, v) + 0.5) / v.size
    out[~valid] = np.nan
    return out


def _grid_comparison(man, grid, dem, train_views, views_b, cfg, subarea_m, work, log) -> dict:
    fp = footprint_mask(man, grid)
    l, b, r, t = grid.bounds
    cx, cy = 0.5 * (l + r), 0.5 * (b + t)
    half = 0.5 * subarea_m
    sub = AOIGrid.from_bounds(cx - half, cy - half, cx + half, cy + half, grid.posting_m, grid.crs)
    z0 = float(np.nanmin(dem)) - 3.0
    z1 = float(np.nanmax(dem)) + cfg.above_m
    geom_full, _ = geometry_from_manifest(
        man, finest_cell_m=cfg.finest_cell_m, max_depth=cfg.max_depth, above_m=cfg.above_m
    )
    geom = geometry_for_aoi(
        sub, z_min_m=z0, z_max_m=z1, finest_cell_m=cfg.finest_cell_m, max_depth=cfg.max_depth, frame=geom_full.frame
    )
    out: dict[str, Any] = {"subarea_bounds": list(sub.bounds), "subarea_m": subarea_m}
    models = {}
    for kind in ("octree", "fixed grid"):
        log(f"sub-area {subarea_m:.0f} m, {kind}:")
        m, tr = train(
            train_views,
            geom,
            sub,
            dem_sub(dem, grid, sub),
            cfg,
            fixed_grid=(kind == "fixed grid"),
            footprints=None if fp is None else dem_sub(fp, grid, sub),
            log=log,
        )
        models[kind] = m
        out[kind] = {"bytes": m.nbytes(), "nodes": m.n_nodes, "leaves": m.n_leaves, **tr}
    out["storage_ratio"] = out["fixed grid"]["bytes"] / out["octree"]["bytes"]
    aucs = {"octree": [], "fixed grid": []}
    for v in views_b:
        truth = read_image(man.root / man.truth["image_masks"][v.name]).data[0] > 0
        dets = {
            k: detect_change(m, v.intensity, v.camera, sun=v.sun, name=v.name, params=DetectParams(neighborhood=1))
            for k, m in models.items()
        }
        valid = ~dets["octree"].unknown & ~dets["fixed grid"].unknown
        for k, d in dets.items():
            aucs[k].append(roc_curve(d.probability, truth, valid)[3])
    out["auc_per_image"] = aucs
    out["auc_mean"] = {k: float(np.mean(v)) for k, v in aucs.items()}
    log(
        f"sub-area: storage ratio {out['storage_ratio']:.1f}x, AUC octree {out['auc_mean']['octree']:.3f}, "
        f"fixed grid {out['auc_mean']['fixed grid']:.3f}"
    )
    return out


def subarea_aucs(
    scene: str,
    bounds: tuple[float, float, float, float],
    *,
    holdout: str = "A_sat3",
    cfg: TrainConfig | None = None,
    shadow_dsm_path: str | None = None,
    log=print,
) -> dict:
    """Pooled per-pixel AUCs of the octree (plain eq. 27 and the default detection) and both 2-D baselines on a sub-area.

    The octree is trained on ``bounds`` (AOI CRS) only, so this is a fast, reduced version of
    :func:`evaluate` for tests; every method is scored on the same pixels (known to the model,
    defined for the baselines) of every epoch-B satellite image.
    """
    return subarea_aucs_by_shadow(scene, bounds, [shadow_dsm_path], holdout=holdout, cfg=cfg, log=log)[0]


def subarea_aucs_by_shadow(
    scene: str,
    bounds: tuple[float, float, float, float],
    shadow_dsm_paths: list[str | None],
    *,
    holdout: str = "A_sat3",
    cfg: TrainConfig | None = None,
    log=print,
) -> list[dict]:
    """:func:`subarea_aucs` for each of ``shadow_dsm_paths`` (None: the model's own shadows), one dict each.

    The model is trained once (training does not depend on the shadow DSM, which only the relit detections use)
    and the 2-D baselines are computed once per image, so each dict equals what :func:`subarea_aucs` gives with
    that ``shadow_dsm_path``.
    """
    cfg = cfg or TrainConfig()
    man = load_manifest(scene)
    geom_full, grid = geometry_from_manifest(
        man, finest_cell_m=cfg.finest_cell_m, max_depth=cfg.max_depth, above_m=cfg.above_m
    )
    dem = read_dem(man.dem.path, grid=grid, vertical_datum=man.dem.vertical_datum).to_ellipsoidal().height_m
    sub = AOIGrid.from_bounds(*bounds, grid.posting_m, grid.crs)
    geom = geometry_for_aoi(
        sub,
        z_min_m=float(np.nanmin(dem)) - 3.0,
        z_max_m=float(np.nanmax(dem)) + cfg.above_m,
        finest_cell_m=cfg.finest_cell_m,
        max_depth=cfg.max_depth,
        frame=geom_full.frame,
    )
    views_a = [read_view(s.path, s.camera, name=s.name) for s in man.epoch("A").images]
    views_b = [read_view(s.path, s.camera, name=s.name) for s in man.epoch("B").images if "sat" in s.name]
    fp = footprint_mask(man, grid)
    shadows = [read_shadow_dsm(p, sub) if p else None for p in shadow_dsm_paths]
    model, _ = train(
        [v for v in views_a if v.name != holdout],
        geom,
        sub,
        dem_sub(dem, grid, sub),
        cfg,
        footprints=None if fp is None else dem_sub(fp, grid, sub),
        log=log,
    )
    ref_pool = [v for v in views_a if "sat" in v.name and v.name != holdout]
    pooled: list[dict[str, list]] = [{} for _ in shadows]
    for v in views_b:
        truth = read_image(man.root / man.truth["image_masks"][v.name]).data[0] > 0
        ref = ref_pool[nearest_view(v.camera, v.intensity.shape, ref_pool, geom)]
        warped = warp_reference(v.camera, v.intensity.shape, ref.intensity, ref.camera, dem, grid)
        baselines = {
            "2-D DEM warp + difference": difference_score(v.intensity, warped),
            "2-D Carlotto joint histogram": carlotto_score(v.intensity, warped),
        }
        for shadow, pool in zip(shadows, pooled):
            # the default 3×3 detection; its plain per-pixel probability comes from the same ray pass
            d3 = detect_change(model, v.intensity, v.camera, sun=v.sun, name=v.name, shadow_dsm=shadow)
            scores = {"3-D octree (relit)": d3.probability_1x1, "3-D octree 3×3 (relit)": d3.probability, **baselines}
            valid = ~d3.unknown & np.all([np.isfinite(sc) for sc in scores.values()], axis=0)
            for k, sc in scores.items():
                pool.setdefault(k, []).append((sc[valid], truth[valid]))
    res = []
    for pool in pooled:
        out = {}
        for k, parts in pool.items():
            t = np.concatenate([p[1] for p in parts])
            out[k] = _roc(np.concatenate([p[0] for p in parts]), t, np.ones(t.size, bool))["auc"]
        out["n_pixels"] = int(t.size)
        out["changed_fraction"] = float(t.mean())
        res.append(out)
    return res


def footprint_mask(man, grid: AOIGrid) -> np.ndarray | None:
    """The manifest's footprints (the training date's) rasterized on ``grid``; None without any."""
    if man.footprints is None:
        return None
    from ..io.vector import polygons_to_mask, read_footprints

    return polygons_to_mask(
        read_footprints(man.footprints.path, crs=grid.crs, layer=man.footprints.layer), grid
    ).astype(bool)


def dem_sub(dem: np.ndarray, grid: AOIGrid, sub: AOIGrid) -> np.ndarray:
    r0, c0 = (
        int(round(v)) for v in grid.rowcol(sub.transform.c + 0.5 * sub.posting_m, sub.transform.f - 0.5 * sub.posting_m)
    )
    return dem[r0 : r0 + sub.height, c0 : c0 + sub.width]


def _json(o):
    if isinstance(o, np.ndarray):
        return None  # curves are in the figures, not the JSON
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def _save_maps(fig, axes, path: Path) -> None:
    """Write a row of map panels (no axis ticks) and close the figure."""
    import matplotlib.pyplot as plt

    for a in axes:
        a.set_xticks([])
        a.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _figures(out: Path, figs: dict, curves: dict, res: dict, agg: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # ROC
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.2))
    styles = {
        "3-D octree (relit)": ("C0", "-"),
        "3-D octree (nearest sun bin)": ("C0", ":"),
        "3-D octree 3×3 (relit)": ("C2", "-"),
        "2-D DEM warp + difference": ("C3", "--"),
        "2-D Carlotto joint histogram": ("C1", "--"),
    }
    for ax, which, title in ((axes[0], 0, "per pixel (eq. 27)"), (axes[1], 1, f"{agg}×{agg} log-odds aggregation")):
        for name, rr in curves.items():
            c, ls = styles.get(name, ("k", "-"))
            r = rr[which]
            ax.plot(r["fpr"], r["tpr"], color=c, ls=ls, label=f"{name}  AUC {r['auc']:.3f}")
        ax.plot([0, 1], [0, 1], color="0.7", lw=0.8)
        ax.set_xlabel("false-positive rate")
        ax.set_ylabel("true-positive rate")
        ax.set_title(f"epoch-B satellite views, pooled: {title}", fontsize=10)
        ax.legend(fontsize=8, loc="lower right")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "volume_roc.png", dpi=110)
    plt.close(fig)
    if "maps" in figs:
        v, truth, p3, carl, zone, expv = figs["maps"]
        fig, ax = plt.subplots(1, 5, figsize=(22, 4.8))
        ax[0].imshow(v.intensity, cmap="gray", vmin=0, vmax=1)
        ax[0].set_title(f"{v.name} (epoch B)")
        ax[1].imshow(expv, cmap="gray", vmin=0, vmax=1)
        ax[1].set_title("expected image (model, relit)")
        ax[2].imshow(truth, cmap="magma")
        ax[2].contour(zone, [0.5], colors="c", linewidths=0.4)
        ax[2].set_title("truth change mask (cyan: edge zone)")
        im = ax[3].imshow(p3, cmap="viridis", vmin=0, vmax=1)
        ax[3].set_title("3-D model P(change)")
        plt.colorbar(im, ax=ax[3], fraction=0.046)
        c = np.clip(carl / np.nanpercentile(carl, 99), 0, 1)
        im = ax[4].imshow(c, cmap="viridis", vmin=0, vmax=1)
        ax[4].set_title("2-D Carlotto residual (scaled)")
        _save_maps(fig, ax, out / "volume_change_maps.png")
    if "expected" in figs:
        real, expv, known = figs["expected"]
        fig, ax = plt.subplots(1, 3, figsize=(15, 5))
        ax[0].imshow(real, cmap="gray", vmin=0, vmax=1)
        ax[0].set_title(f"held-out {res['heldout']['name']} (real)")
        e = np.where(known, expv, np.nan)
        ax[1].imshow(e, cmap="gray", vmin=0, vmax=1)
        ax[1].set_title(f"expected image, PSNR {res['heldout']['psnr_db']:.1f} dB")
        im = ax[2].imshow(np.abs(e - real), cmap="magma", vmin=0, vmax=0.5)
        ax[2].set_title("|expected − real|")
        plt.colorbar(im, ax=ax[2], fraction=0.046)
        _save_maps(fig, ax, out / "volume_expected.png")
    if "height" in figs:
        h, dsm = figs["height"]
        lo, hi = np.nanpercentile(dsm, [1, 99.5])
        fig, ax = plt.subplots(1, 3, figsize=(16, 5))
        for a, arr, t in ((ax[0], h, "expected height map (model)"), (ax[1], dsm, "truth DSM (epoch A)")):
            im = a.imshow(arr, cmap="terrain", vmin=lo, vmax=hi)
            a.set_title(t)
            plt.colorbar(im, ax=a, fraction=0.046, label="m (ellipsoidal)")
        im = ax[2].imshow(h - dsm, cmap="RdBu_r", vmin=-4, vmax=4)
        ax[2].set_title(f"model − truth, median |Δz| {res['height_map']['median_abs_dz_m']:.2f} m")
        plt.colorbar(im, ax=ax[2], fraction=0.046, label="m")
        _save_maps(fig, ax, out / "volume_height.png")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", help="manifest or scene folder with truth (e.g. sample_aoi)")
    ap.add_argument("--out", default="./geocd_out/volume_eval", help="folder for volume_*.png and volume_results.json")
    ap.add_argument("--work", default=None, help="folder for the trained model (default: OUT/work)")
    ap.add_argument("--holdout", default="A_sat3")
    ap.add_argument("--passes", type=int, default=5)
    ap.add_argument("--finest", type=float, default=0.5)
    ap.add_argument("--subarea", type=float, default=150.0, help="side of the octree/grid comparison area (m)")
    ap.add_argument("--no-grid", action="store_true")
    ap.add_argument("--no-dem-prior", action="store_true")
    ap.add_argument(
        "--footprints",
        action="store_true",
        help="DEM prior: roof heights swept from the manifest's footprints (see docs/volume.md)",
    )
    ap.add_argument("--ground-band", type=float, default=0.5, help="DEM prior: ground band half-height (m)")
    ap.add_argument(
        "--ground-band-top", type=float, default=0.0, help="DEM prior: top of the ground band above the DEM (m)"
    )
    ap.add_argument(
        "--ground-p-max", type=float, default=0.9, help="DEM prior: cap of a ground-band cell's occlusion probability"
    )
    ap.add_argument(
        "--shadow-dsm",
        default=None,
        help="a DSM of epoch A (e.g. geocd ortho's dsm_A.tif): the relighting casts its shadows",
    )
    a = ap.parse_args(argv)
    cfg = TrainConfig(
        passes=a.passes,
        finest_cell_m=a.finest,
        dem_prior=not a.no_dem_prior,
        ground_band_m=a.ground_band,
        ground_band_top_m=a.ground_band_top,
        ground_p_max=a.ground_p_max,
        footprints=a.footprints,
    )
    t0 = time.perf_counter()
    res = evaluate(
        a.scene,
        a.out,
        a.work if a.work is not None else str(Path(a.out) / "work"),
        holdout=a.holdout,
        cfg=cfg,
        subarea_m=a.subarea,
        do_grid=not a.no_grid,
        shadow_dsm_path=a.shadow_dsm,
        log=lambda m: print(m, flush=True),
    )
    print(
        json.dumps({k: res[k] for k in ("heldout", "height_map", "change_pooled") if k in res}, indent=1, default=_json)
    )
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
