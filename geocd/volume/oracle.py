"""What a *perfect* model of epoch A scores per pixel on a generated scene: the ceiling of image-vs-model change.

The octree model (:func:`geocd.volume.detect_change`) predicts each pixel of an epoch-B image from epoch A's
appearance, relit by one robust line per lit/shadow transition class (:mod:`geocd.volume.relight`). On a scene
made by ``geocd synth`` the simulator can stand in for a perfect model: it renders the noise-free epoch A from
each B view's exact camera, so there is no registration error, no model error and no unknown appearance.
:func:`perfect_model_aucs` scores the B image against such renders on the per-image truth masks of
``python -m geocd.volume.evaluate``:

* ``perfect A, A's sun, one line``: epoch A rendered under A's sun, one robust line ``c ≈ a + b E`` over the
  image;
* ``perfect A, A's sun, exact class lines``: the same with the relighting's four lit/shadow classes taken from
  the simulator (a pixel is lit under a sun when its first hit receives direct light). This is the best the
  octree's relighting form can do with a perfect 3-D model and perfect shadow classes;
* ``perfect A, B's sun, one line``: epoch A rendered under B's sun, a relighting that knows every surface's
  orientation and albedo exactly, sub-cell texture included;
* the two class-line renders again with the 3 × 3 detection of the octree's default: a pixel's score is the
  lowest over its 3 × 3 neighbours' predictions;
* optionally the octree model itself (``octree_work``): trained as the evaluation trains it (A_sat3 held out)
  and saved there, or reused; its default 3 × 3 detection, with a shadow DSM when given. Every figure is then
  taken on the pixels the model knows;
* the evaluation's two 2-D baselines (Carlotto's joint histogram, DEM warp + difference).

The renders use the generator's own cameras, suns, pan weights and 0.5-pixel sensor blur, and equalised
intensities like every geocd input. A score is the pixel's Gaussian negative log-density under its class's
line (higher means change). Pixels are those of the B image whose ray meets the truth DSM of B inside the AOI,
where the 2-D baselines are defined. The changed pixels are also split by what changed under each pixel's
centre ray (:data:`CHANGE_KINDS`): a building whose height changed (same building in both epochs), a building
new or gone, a car, a tree, or other (occlusion, mixed pixel). Each kind is scored against every unchanged pixel,
and so is every changed pixel but the roofs whose height changed.

This is evaluation code for generated scenes only (it needs the simulator's scene). Run::

    python -m geocd.volume.oracle SCENE OUT.json [--octree WORK [--shadow-dsm DSM]]

Figures: docs/volume.md, "The ceiling: a perfect model of epoch A".
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter

from ..errors import ConfigError, ManifestError
from ..io.atomic import write_text_atomic
from ..io.manifest import load_manifest
from ..io.raster import read_dem, read_image
from ..synth import scene as synth_scene
from ..synth.generate import SynthParams, make_satellite_cameras
from ..synth.render import PAN_WEIGHTS, RenderParams, pack_scene, render_view, trace_view
from ..synth.sensors import Sun
from .baseline import carlotto_score, difference_score, edge_zone, first_surface_height, nearest_view, warp_reference
from .detect import DetectParams, detect_change
from .evaluate import TrainConfig, _roc, footprint_mask, train
from .io import geometry_from_manifest, load_model, read_shadow_dsm, read_view, save_model
from .relight import CLASSES, robust_line

CHANGE_KINDS = ("building height", "building new or gone", "car", "tree", "other (occlusion, mixed pixel)")
PERFECT_ROWS = (
    "perfect A, A's sun, one line",
    "perfect A, A's sun, exact class lines",
    "perfect A, B's sun, one line",
    "perfect A, A's sun, exact class lines, 3×3",
    "perfect A, B's sun, one line, 3×3",
)
BASELINE_ROWS = ("2-D Carlotto joint histogram", "2-D DEM warp + difference")


def equalize(g: np.ndarray) -> np.ndarray:
    """Rank of each pixel in [0, 1]: ``image_intensity(..., normalize="equalize")`` of a float image (rows, cols)."""
    v = g.ravel()
    srt = np.sort(v)
    rank = 0.5 * (np.searchsorted(srt, v, "left") + np.searchsorted(srt, v, "right"))
    return (rank / v.size).reshape(g.shape)


def pan(radiance: np.ndarray, blur_px: float) -> np.ndarray:
    """The simulator's pan band of a (4, rows, cols) radiance image, blurred by the sensor's PSF (σ in pixels)."""
    img = np.tensordot(PAN_WEIGHTS, radiance.astype(np.float64), axes=1)
    return gaussian_filter(img, blur_px, mode="nearest") if blur_px > 0 else img


def change_kind(town, camera, scene_a, scene_b, shape: tuple[int, int]) -> np.ndarray:
    """What each pixel's centre ray sees change: int (rows, cols), an index into :data:`CHANGE_KINDS`, or -1
    where the first hits of the two epochs lie within 1 m of each other."""
    rows, cols = shape
    R, C = np.mgrid[0:rows, 0:cols]
    (pa, oa), (pb, ob) = (trace_view(town, camera, S, C.ravel() + 0.5, R.ravel() + 0.5) for S in (scene_a, scene_b))
    moved = np.linalg.norm(pa - pb, axis=1) > 1.0
    cls = [np.where(o >= 0, S.cls[np.maximum(o, 0)], -1) for o, S in ((oa, scene_a), (ob, scene_b))]
    ident = [np.where(o >= 0, S.par[np.maximum(o, 0), 3], -1) for o, S in ((oa, scene_a), (ob, scene_b))]
    car = (cls[0] == synth_scene.C_CAR) | (cls[1] == synth_scene.C_CAR)
    tree = ~car & ((cls[0] == synth_scene.C_TREE) | (cls[1] == synth_scene.C_TREE))
    bld = [c == synth_scene.C_BUILDING for c in cls]
    same = bld[0] & bld[1] & (ident[0] == ident[1])
    kind = np.full(pa.shape[0], 4)
    kind[same & ~car & ~tree] = 0
    kind[~car & ~tree & (bld[0] | bld[1]) & ~same] = 1
    kind[car] = 2
    kind[tree] = 3
    kind[~moved] = -1
    return kind.reshape(shape)


def neg_log_density(
    c: np.ndarray, e: np.ndarray, klass: np.ndarray, fit_on: np.ndarray, half: int = 0
) -> tuple[np.ndarray, dict]:
    """−log N(c; a_k + b_k e, σ_k), one robust line per class k fitted on the pixels ``fit_on``.

    Parameters
    ----------
    c, e : float (rows, cols), the observed and the predicted intensity
    klass : int (rows, cols), 0..3 (:data:`geocd.volume.relight.CLASSES`)
    fit_on : bool (rows, cols)
    half : the lowest over the (2 half + 1)² neighbours' predictions (the neighbour's e and class, the pixel's
        c), as the octree's n × n detection takes the highest density over its neighbours' rays

    Returns
    -------
    (score (rows, cols), {class: {a, b, sigma, pixels}})
    """
    lines = {}
    par = np.zeros((4, 3))
    par[:, 2] = 1.0
    for k in np.unique(klass[fit_on]):
        sel = fit_on & (klass == k)
        if sel.sum() < 200:
            sel = fit_on
        a, b, s = robust_line(e[sel], c[sel])
        par[k] = a, b, max(s, 1e-3)
        lines[int(k)] = {
            "a": round(a, 4),
            "b": round(b, 4),
            "sigma": round(float(par[k, 2]), 4),
            "pixels": int(sel.sum()),
        }
    out = np.full(c.shape, np.inf)
    pe = np.pad(e, half, mode="edge")
    pk = np.pad(klass, half, mode="edge")
    rows, cols = c.shape
    for dr in range(2 * half + 1):
        for dc in range(2 * half + 1):
            en, kn = pe[dr : dr + rows, dc : dc + cols], pk[dr : dr + rows, dc : dc + cols]
            a, b, s = par[kn, 0], par[kn, 1], par[kn, 2]
            out = np.minimum(out, 0.5 * ((c - a - b * en) / s) ** 2 + np.log(s))
    return out, lines


def perfect_model_aucs(
    scene: str | Path,
    *,
    views: list[str] | None = None,
    octree_work: str | Path | None = None,
    shadow_dsm_path: str | Path | None = None,
    blur_px: float = 0.5,
    log=print,
) -> dict[str, Any]:
    """Per-pixel AUCs of a perfect epoch-A model, the 2-D baselines and optionally the octree (module doc).

    Parameters
    ----------
    scene : a folder written by ``geocd synth`` (scene.yaml, images, truth/scene_truth.json)
    views : epoch-B satellite image names to score (default: all)
    octree_work : folder of the octree model (``volume_octree`` in it is trained when absent)
    shadow_dsm_path : a DSM of epoch A for the octree's relighting (``geocd ortho``'s ``dsm_A.tif``)
    blur_px : the sensor's PSF σ in pixels (``SensorRadiometry.psf_sigma_px``)

    Returns
    -------
    dict: suns, per view and pooled AUCs (all pixels, edge zone, outside it, per shadow class and per change
    kind), the fitted lines.
    """
    t_all = time.perf_counter()
    root = Path(scene)
    truth_file = root / "truth" / "scene_truth.json"
    if not truth_file.is_file():
        raise ManifestError(
            f"{root} has no truth/scene_truth.json: the perfect model needs a scene made by "
            "geocd synth (give such a folder)"
        )
    man = load_manifest(str(root / "scene.yaml"))
    names_b = [s.name for s in man.epoch("B").images if "sat" in s.name and (views is None or s.name in views)]
    if not names_b:
        raise ConfigError(f"no epoch-B satellite view of {root} is among {views}")
    truth = json.loads(truth_file.read_text())
    sp = SynthParams.from_dict(truth["params"])
    town = synth_scene.build_town(sp.town_params())
    suns = {ep: Sun(**truth["sun"][ep]) for ep in ("A", "B")}  # the suns the generator rendered with
    cams = make_satellite_cameras(sp, town)
    scene_a, scene_b = pack_scene(town, "A"), pack_scene(town, "B")
    cfg = TrainConfig()
    geom, grid = geometry_from_manifest(
        man, finest_cell_m=cfg.finest_cell_m, max_depth=cfg.max_depth, above_m=cfg.above_m
    )
    dem = read_dem(man.dem.path, grid=grid, vertical_datum=man.dem.vertical_datum).to_ellipsoidal().height_m
    dsm_b = read_dem(man.truth_path("dsm_B"), grid=grid).height_m
    views_a = [read_view(s.path, s.camera, name=s.name) for s in man.epoch("A").images]
    ref_pool = [v for v in views_a if "sat" in v.name and v.name != "A_sat3"]
    views_b = [read_view(s.path, s.camera, name=s.name) for s in man.epoch("B").images if s.name in names_b]
    rows_out = PERFECT_ROWS + BASELINE_ROWS
    model = shadow = None
    if octree_work is not None:
        work = Path(octree_work)
        if (work / "volume_octree").exists():
            model = load_model(work / "volume_octree")
        else:
            model, _ = train(
                [v for v in views_a if v.name != "A_sat3"],
                geom,
                grid,
                dem,
                cfg,
                footprints=footprint_mask(man, grid) if cfg.footprints else None,
                log=log,
            )
            save_model(model, work / "volume_octree")
        shadow = read_shadow_dsm(shadow_dsm_path, grid) if shadow_dsm_path else None
        rows_out += ("3-D octree 3×3 (relit, " + ("DSM shadows)" if shadow is not None else "model's shadows)"),)
    pooled: dict[str, list] = {k: [] for k in rows_out}
    per_view = []
    for v in views_b:
        t0 = time.perf_counter()
        cam = cams[v.name]
        shape = v.intensity.shape
        changed = read_image(root / man.truth["image_masks"][v.name]).data[0] > 0

        def render(sun_epoch: str, **kw) -> np.ndarray:
            return render_view(
                town, "A", cam, suns[sun_epoch].direction_enu(), RenderParams(**kw), scene=scene_a
            ).radiance

        e_a = equalize(pan(render("A", supersample=2), blur_px))
        e_ab = equalize(pan(render("B", supersample=2), blur_px))
        lit = [render(ep, supersample=1, sky_irradiance=0.0).sum(axis=0) > 0 for ep in ("A", "B")]
        klass = (~lit[0]).astype(int) * 2 + (~lit[1]).astype(int)  # the order of relight.CLASSES
        ref = ref_pool[nearest_view(v.camera, shape, ref_pool, geom)]
        warped = warp_reference(v.camera, shape, ref.intensity, ref.camera, dem, grid)
        diff = difference_score(v.intensity, warped)
        carl = carlotto_score(v.intensity, warped)
        first = first_surface_height(v.camera, shape, dsm_b, grid, geom)
        zone = edge_zone(first)
        valid = np.isfinite(first) & np.isfinite(v.intensity) & np.isfinite(diff) & np.isfinite(carl)
        ckind = change_kind(town, cam, scene_a, scene_b, shape)
        c = v.intensity
        one = np.zeros(shape, int)
        s_one, l_one = neg_log_density(c, e_a, one, valid)
        s_cls, l_cls = neg_log_density(c, e_a, klass, valid)
        s_ab, l_ab = neg_log_density(c, e_ab, one, valid)
        s_cls3, _ = neg_log_density(c, e_a, klass, valid, half=1)
        s_ab3, _ = neg_log_density(c, e_ab, one, valid, half=1)
        scores = dict(zip(rows_out, (s_one, s_cls, s_ab, s_cls3, s_ab3, carl, diff)))
        if model is not None:
            det = detect_change(
                model,
                v.intensity,
                v.camera,
                sun=v.sun,
                name=v.name,
                params=DetectParams(neighborhood=3),
                shadow_dsm=shadow,
            )
            valid &= ~det.unknown
            scores[rows_out[-1]] = det.probability
        entry = {
            "name": v.name,
            "pixels": int(valid.sum()),
            "changed_fraction": round(float(changed[valid].mean()), 4),
            "class_fraction": {CLASSES[k]: round(float((klass[valid] == k).mean()), 4) for k in range(4)},
            "class_lines": {CLASSES[k]: line for k, line in l_cls.items()},
            "line_A_sun": l_one[0],
            "line_B_sun": l_ab[0],
            "auc": {},
            "auc_edge_zone": {},
            "auc_outside_edge_zone": {},
        }
        for name, sc in scores.items():
            entry["auc"][name] = round(_roc(sc, changed, valid)["auc"], 4)
            entry["auc_edge_zone"][name] = round(_roc(sc, changed, valid & zone)["auc"], 4)
            entry["auc_outside_edge_zone"][name] = round(_roc(sc, changed, valid & ~zone)["auc"], 4)
            pooled[name].append((sc[valid], changed[valid], zone[valid], klass[valid], ckind[valid]))
        entry["seconds"] = round(time.perf_counter() - t0, 1)
        per_view.append(entry)
        log(f"{v.name}: " + ", ".join(f"{k} {a:.3f}" for k, a in entry["auc"].items()))
    res: dict[str, Any] = {
        "scene": str(root),
        "suns": {ep: [round(suns[ep].azimuth_deg, 1), round(suns[ep].elevation_deg, 1)] for ep in ("A", "B")},
        "shadow_dsm": None if shadow_dsm_path is None else str(shadow_dsm_path),
        "views": per_view,
        "pooled": {},
    }
    for name, parts in pooled.items():
        s, t, z, k, ck = (np.concatenate([p[i] for p in parts]) for i in range(5))
        entry = {
            "auc": round(_roc(s, t, np.ones(t.size, bool))["auc"], 4),
            "edge_zone": round(_roc(s, t, z)["auc"], 4),
            "outside_edge_zone": round(_roc(s, t, ~z)["auc"], 4),
        }
        entry.update({CLASSES[i]: round(_roc(s, t, k == i)["auc"], 4) for i in range(4) if (t & (k == i)).any()})
        # what an image can show: every changed pixel but the roofs whose height changed
        entry["without roofs whose height changed"] = round(_roc(s, t, ~t | (ck != 0))["auc"], 4)
        # the changed pixels of one kind against every unchanged pixel
        entry["by change kind"] = {
            CHANGE_KINDS[j]: {
                "share_of_changed": round(float((t & (ck == j)).sum() / t.sum()), 3),
                "auc": round(_roc(s, t, ~t | (ck == j))["auc"], 4),
            }
            for j in range(len(CHANGE_KINDS))
            if (t & (ck == j)).any()
        }
        res["pooled"][name] = entry
    res["seconds"] = round(time.perf_counter() - t_all, 1)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m geocd.volume.oracle", description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="a folder written by geocd synth")
    ap.add_argument("out", help="JSON file to write")
    ap.add_argument("--view", action="append", default=None, help="an epoch-B satellite view (repeatable; default all)")
    ap.add_argument(
        "--octree",
        default=None,
        metavar="WORK",
        help="add the octree model's 3×3 detection (trained into WORK/volume_octree unless it is there)",
    )
    ap.add_argument(
        "--shadow-dsm", default=None, help="a DSM of epoch A whose cast shadows the octree's relighting uses"
    )
    ap.add_argument("--blur-px", type=float, default=0.5, help="the sensor's PSF σ in pixels")
    a = ap.parse_args(argv)
    res = perfect_model_aucs(
        a.scene,
        views=a.view,
        octree_work=a.octree,
        shadow_dsm_path=a.shadow_dsm,
        blur_px=a.blur_px,
        log=lambda m: print(m, flush=True),
    )
    write_text_atomic(Path(a.out), json.dumps(res, indent=1) + "\n")
    print(json.dumps({k: v["auc"] for k, v in res["pooled"].items()}, indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
