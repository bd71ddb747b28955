"""Evaluate the self-consistency change test on sample_aoi (issue 5's Show list).

Prints, for the run on sample_aoi:

* cell-level precision / recall / F1 / false-alarm rate (cells with no 3-D change that are flagged)
  for the self-consistency test at 90/95/99% and for the paper's naive thresholds |Δ̃| > 3 and > 6
  (its Fig. 1 c, d), plus |Δz| thresholds in metres;
* building-level F1 of the building layer ``geocd run`` writes (:func:`geocd.pipeline.run_building_layer`)
  from the epoch-A footprints only (new buildings must be detected) against every building's truth status
  (:func:`geocd.change.buildings.score_buildings`: collapsed / partly collapsed / lowered / raised / new count
  as changed, unchanged and unobserved as not changed; the unobserved count is printed beside). For the other
  maps of the table (other levels, per-cell test, naive thresholds) the same layer is made from that map as the
  reported one (:class:`geocd.change.dsm_buildings.LevelMasks`);
* the one-pair-per-epoch case with a curve learned on another sample scene (``--other-scene``).

Usage::

    .venv/bin/python bench/eval_self_consistency.py [--run-dir OUT] [--other-scene DIR] [--json out.json]

``--run-dir`` reuses a finished ``geocd run sample_aoi --out OUT`` (pair-DEMs are read from OUT/stereo);
otherwise the run is done here.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def load_pairs(run_dir: Path):
    from geocd.stereo import read_pair_dem

    pairs = [read_pair_dem(p) for p in sorted((run_dir / "stereo").rglob("*.tif"))]
    by: dict[str, list] = {}
    for p in pairs:
        by.setdefault(p.epoch, []).append(p)
    return by


def truth_on(grid, path, resampling="nearest"):
    from geocd.io.raster import read_on_grid

    return read_on_grid(path, grid, resampling=resampling)


def cell_table(A, B, model, truth_change, levels=(90.0, 95.0, 99.0), significance="region"):
    """Cell-level scores; also returns the signed masks (for the building-level table)."""
    from geocd.change.metrics import binary_scores
    from geocd.consistency import ChangeParams, change_test, naive_threshold

    res = change_test(A, B, model, ChangeParams(confidences=levels, significance=significance))
    cell = change_test(A, B, model, ChangeParams(confidences=levels, significance="cell"))
    obs = res.observed
    rows, masks = [], {}
    for lev in levels:
        masks["self-consistency %g%%" % lev] = res.changed_at(lev)
    for lev in levels:
        masks["per-cell test %g%%" % lev] = cell.changed_at(lev)
    for thr in (3.0, 6.0):
        masks[f"naive |Δ̃| > {thr:g} px"] = naive_threshold(
            A, B, thr, units="dtilde", min_region_cells=res.min_region_cells
        )
    for thr in (1.0, 2.0, 3.0):
        masks[f"naive |Δz| > {thr:g} m"] = naive_threshold(A, B, thr, units="m", min_region_cells=res.min_region_cells)
    for name, m in masks.items():
        rows.append((name, binary_scores((m != 0) & (m != -128), truth_change, obs)))
    return res, rows, masks


def print_rows(title, rows):
    print(f"\n{title}")
    print(f"{'method':28s} {'precision':>9s} {'recall':>7s} {'F1':>6s} {'false alarms':>12s} {'cells':>8s}")
    for name, s in rows:
        print(
            f"{name:28s} {s['precision']:9.3f} {s['recall']:7.3f} {s['f1']:6.3f} {100 * s['false_alarm_rate']:11.2f}% "
            f"{s['n']:8d}"
        )


def building_eval(mask, res, grid, A, B, scene_manifest, model=None):
    """The building layer of ``geocd run`` from the epoch-A footprints (new ones detected), scored against every
    building's status. ``mask``: None for ``res`` itself at the reported 99 %, else a signed change map the
    layer is made from instead (as its reported level)."""
    from shapely.geometry import box

    from geocd.change.buildings import score_buildings
    from geocd.change.dsm_buildings import LevelMasks
    from geocd.io.vector import read_footprints
    from geocd.pipeline import RunConfig, run_building_layer

    cfg = RunConfig()
    fa = read_footprints(scene_manifest.truth_path("footprints_A"), crs=grid.crs)
    fall = read_footprints(scene_manifest.truth_path("footprints_all"), crs=grid.crs)
    if mask is not None:
        res = LevelMasks(res.dz_m, {cfg.region_confidence: mask}, res.min_region_cells)
    b, _ = run_building_layer(fa, res, grid, A, B, model if mask is None else None, cfg)
    s = score_buildings(b, fall, aoi=box(*grid.bounds))
    s["unobserved"] = int(b["class"].isin(["unobserved", "not examined"]).sum())
    status = dict(zip(fall["building_id"], fall["status"]))
    conf = {}
    for _, row in b.iterrows():
        t = status.get(row["building_id"], "detected") if row["source"] == "footprints" else "detected"
        conf.setdefault(t, {}).setdefault(row["class"], 0)
        conf[t][row["class"]] += 1
    return s, conf


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default=str(REPO / "sample_aoi"))
    ap.add_argument("--run-dir", default=None)
    ap.add_argument("--other-scene", default=None, help="a second sample scene (another seed) to learn a model from")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()

    from geocd.consistency import learn_self_consistency
    from geocd.io.manifest import load_manifest

    m = load_manifest(args.scene)
    out: dict = {}
    if args.run_dir is None:
        from geocd.pipeline import run

        t0 = time.perf_counter()
        run_dir = Path("/tmp/geocd_eval_sc")
        run(m, out_dir=run_dir)
        out["run_wall_s"] = time.perf_counter() - t0
    else:
        run_dir = Path(args.run_dir)
    by = load_pairs(run_dir)
    A, B = by["A"], by["B"]
    grid = A[0].grid
    truth = truth_on(grid, m.truth_path("change_mask")) > 0.5
    model = learn_self_consistency([A, B])
    res, rows, masks = cell_table(A, B, model, truth)
    print_rows(f"{m.name}, all pairs (A: {len(A)} pair-DEMs, B: {len(B)}), cells observed in both epochs", rows)
    out["cells_all_pairs"] = {n: s for n, s in rows}
    print("\nbuildings (epoch-A footprints; new buildings detected outside them; truth: every building's status)")
    print(f"{'method':28s} {'precision':>9s} {'recall':>7s} {'F1':>6s} {'class acc.':>10s}  tp fp fn unobserved")
    out["buildings"] = {}
    for name, mk in masks.items():
        reported = name == "self-consistency 99%"
        s, conf = building_eval(None if reported else mk, res, grid, A, B, m, model=model)
        out["buildings"][name] = s
        print(
            f"{name:28s} {s['precision']:9.3f} {s['recall']:7.3f} {s['f1']:6.3f} {s['class_accuracy_on_changed']:10.3f}"
            f"  {s['tp']:2d} {s['fp']:2d} {s['fn']:2d} {s['unobserved']:2d}"
        )
        if name == "self-consistency 99%":
            out["buildings_confusion_99"] = conf
    print("self-consistency 99%, truth → predicted:", json.dumps(out["buildings_confusion_99"]))

    # satellite-only pairs (the SRI satellite case) and one pair per epoch
    sat = lambda ps: [p for p in ps if "air" not in p.name]  # noqa: E731
    A1, B1 = sat(A)[:1], sat(B)[:1]
    if args.other_scene:
        by2 = load_pairs(Path(args.other_scene)) if (Path(args.other_scene) / "stereo").is_dir() else None
        if by2 is None:
            from geocd.stereo.pipeline import run_stereo

            st = run_stereo(args.other_scene, out_dir=Path("/tmp/geocd_eval_other"), keep_arrays=True)
            by2 = {}
            for p in st["pairs"].values():
                by2.setdefault(p.epoch, []).append(p)
        model2 = learn_self_consistency(
            [g for g in by2.values() if len(g) >= 2], provenance={"scene": str(args.other_scene)}
        )
        res1, rows1, masks1 = cell_table(A1, B1, model2, truth)
        print_rows(f"one pair per epoch ({A1[0].name} vs {B1[0].name}), model learned on {args.other_scene}", rows1)
        s1, conf1 = building_eval(None, res1, grid, A1, B1, m, model=model2)
        print(
            f"buildings at 99% (one pair per epoch, other-scene model): F1 {s1['f1']:.3f} "
            f"precision {s1['precision']:.3f} recall {s1['recall']:.3f}"
        )
        out["one_pair_other_model"] = {"cells": {n: s for n, s in rows1}, "buildings_99": s1}
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2, default=float))


if __name__ == "__main__":
    main()
