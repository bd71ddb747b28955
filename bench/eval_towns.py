"""The figures of docs/towns.md: every change method on sample_aoi and generated towns, nothing changed between them.

For each scene (a ``geocd synth`` folder with truth):

* self-consistency (``geocd run``'s defaults): cells precision / recall / F1 / false alarms at 90, 95 and 99 %
  against ``truth/change_mask.tif`` (region test, the default, and the SRI per-cell test), and buildings F1 of
  **the building layer ``geocd run`` writes** (layer ``buildings`` of ``sc_changes.gpkg``, made here by the same
  function, :func:`geocd.pipeline.run_building_layer`, at the reported 99 %) from the scene's footprints — the
  **epoch-A footprints only** (``truth/footprints_A.gpkg``, the manifest's), so new buildings must be detected.

How the layer is scored (:func:`geocd.change.buildings.score_buildings`, truth: every building's ``status`` in
``truth/footprints_all.gpkg``): a building counts as *changed* when the layer calls it ``collapsed``, ``partly
collapsed`` or ``lowered`` (truth ``demolished`` or ``lowered``), ``raised`` (truth ``raised``) or ``new`` (truth
``new``); ``unchanged``, ``unobserved`` and ``not examined`` count as *not changed*. A footprint row is a true
positive when both the layer and the truth call it changed (whatever the class; the class agreement is
``class_accuracy_on_changed``), a false positive when only the layer does, a false negative when only the truth
does. A new building of the layer (``source`` "change map") is a true positive when it overlaps a truth building
absent from the footprints (inside the AOI), else a false positive; such a truth building that no new building
overlaps is a false negative. So an **unobserved** footprint is a false negative when its building changed and
counts nowhere when it did not: the layer's unobserved count is reported beside the scores (``unobserved``,
``unobserved_changed_in_truth``), and every building scored wrong is listed with its truth status, the layer's
class, ``rule`` and ``source`` (``mistakes``).

``buildings_footprint_rule`` (a second column, JSON only) scores the footprint rule alone
(:func:`geocd.change.buildings.classify_buildings`, the intermediate the layer starts from), as this script
measured before the layer existed; ``buildings_changed_part_on`` the layer with the changed-part rule on.
When ``RUN_DIR/sc_changes.gpkg`` exists, the layer made here is compared class by class with the run's
(``same_classes_as_run``).
* probchange (robust model, object space, satellite views; ``ProbChangeParams.robust()``): pixel F1;
* the octree volume model against its two 2-D baselines, per-pixel AUC pooled over the epoch-B satellite images,
  read from the ``volume_results.json`` that ``python -m geocd.volume.evaluate SCENE --out DIR`` writes.

Usage::

    .venv/bin/python bench/eval_towns.py \\
        --scene sample_aoi=sample_aoi:/tmp/run0 --scene town_seed1=/tmp/town_s1:/tmp/run_s1 ... \\
        [--volume sample_aoi=/tmp/vol_s0/volume_results.json ...] [--no-probchange] \\
        --json bench/results/towns.json --markdown docs/towns_table.md

``NAME=SCENE[:RUN_DIR]``: ``RUN_DIR`` reuses the pair-DEMs of a finished ``geocd run SCENE --out RUN_DIR``
(``RUN_DIR/stereo``); without it the stereo is run here (into a temporary folder).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
LEVELS = (90.0, 95.0, 99.0)


def _pairs(scene: Path, run_dir: Path | None):
    from geocd.io.manifest import load_manifest
    from geocd.pipeline import RunConfig
    from geocd.stereo import read_pair_dem
    from geocd.stereo.pipeline import run_stereo

    m = load_manifest(scene)
    if run_dir is None or not (run_dir / "stereo").is_dir():
        run_dir = run_dir or Path(tempfile.mkdtemp(prefix="geocd_towns_"))
        cfg = RunConfig()
        run_stereo(m, epochs=[e.name for e in m.epochs], out_dir=run_dir, params=cfg.stereo, pairs=cfg.pairs)
    by: dict[str, list] = {}
    for f in sorted((run_dir / "stereo").rglob("*.tif")):
        p = read_pair_dem(f)
        by.setdefault(p.epoch, []).append(p)
    return m, by


def _round(d: dict) -> dict:
    return {k: (round(float(v), 4) if isinstance(v, (float, np.floating)) else v) for k, v in d.items()}


def layer_mistakes(layer, truth, aoi) -> list[dict]:
    """The buildings the layer gets wrong (changed vs not changed), for reading: footprint rows whose truth
    status and layer class disagree, new buildings of the layer overlapping no truth building absent from the
    footprints, and such truth buildings no new building overlaps."""
    from geocd.change.building_layer import CHANGED, SOURCE_FOOTPRINTS

    truth = truth.to_crs(layer.crs)
    status = dict(zip(truth["building_id"], truth["status"]))
    out = []

    def rec(row, st):
        return {
            "building_id": int(row["building_id"]),
            "truth": st,
            "class": str(row["class"]),
            "source": str(row["source"]),
            "rule": str(row["rule"]),
            "frac_observed": _r(row["frac_observed"]),
            "frac_changed": _r(row["frac_changed"]),
            "mean_dz_m": _r(row["mean_dz_m"]),
        }

    fp = layer[layer["source"] == SOURCE_FOOTPRINTS]
    for _, row in fp.iterrows():
        st = status.get(row["building_id"], "unchanged")
        if (st != "unchanged") != (row["class"] in CHANGED):
            out.append(rec(row, st))
    unknown = truth[~truth["building_id"].isin(set(fp["building_id"]))]
    unknown = unknown[(unknown.geometry.intersection(aoi).area / unknown.geometry.area).to_numpy() >= 0.5]
    det = layer[layer["source"] != SOURCE_FOOTPRINTS]
    for _, row in det.iterrows():
        if not (unknown.geometry.intersection(row.geometry).area > 0).any():
            out.append(rec(row, "none (no truth building absent from the footprints here)"))
    for _, t in unknown.iterrows():
        if not (det.geometry.intersection(t.geometry).area > 0).any():
            out.append({"building_id": int(t["building_id"]), "truth": str(t["status"]), "class": "not detected"})
    return out


def _r(v):
    v = float(v)
    return round(v, 3) if np.isfinite(v) else None


def self_consistency(scene: Path, run_dir: Path | None) -> dict:
    from shapely.geometry import box

    from geocd.change.buildings import classify_buildings, score_buildings
    from geocd.change.metrics import binary_scores
    from geocd.consistency import change_test, learn_self_consistency
    from geocd.io.raster import read_on_grid
    from geocd.io.vector import read_footprints
    from geocd.pipeline import RunConfig, run_building_layer
    from geocd.stereo.surface import epoch_surface

    m, by = _pairs(scene, run_dir)
    A, B = by["A"], by["B"]
    grid = A[0].grid
    aoi = box(*grid.bounds)
    truth = read_on_grid(m.truth_path("change_mask"), grid) > 0.5
    cfg = RunConfig()
    t = time.perf_counter()
    model = learn_self_consistency([A, B], cfg.consistency)
    out: dict = {
        "pairs": {k: [p.name for p in v] for k, v in by.items()},
        "mapping_unit_cells": model.region_null.get("min_region_cells"),
        "footprints": Path(m.footprints.path).name,
    }
    # the footprints as geocd run reads them (the manifest's: the epoch-A footprints)
    fa = read_footprints(m.footprints.path, crs=grid.crs, layer=m.footprints.layer)
    fall = read_footprints(m.truth_path("footprints_all"), crs=grid.crs)
    za, zb = epoch_surface(A), epoch_surface(B)
    run_layer = None
    if run_dir is not None and (run_dir / "sc_changes.gpkg").is_file():
        import geopandas as gpd

        run_layer = gpd.read_file(run_dir / "sc_changes.gpkg", layer="buildings")
    for mode in ("region", "cell"):
        change = dataclasses.replace(cfg.change, significance=mode)
        if cfg.region_confidence not in change.confidences:
            change = dataclasses.replace(
                change, confidences=tuple(sorted({*change.confidences, cfg.region_confidence}))
            )
        res = change_test(A, B, model, change)
        cells = {}
        for lev in LEVELS:
            mk = res.changed_at(lev)
            cells[f"{lev:g}"] = _round(binary_scores((mk == 1) | (mk == -1), truth, res.observed))
        layer, _ = run_building_layer(fa, res, grid, A, B, model, cfg)
        cp = dataclasses.replace(cfg, buildings=dataclasses.replace(cfg.buildings, changed_part=True))
        layer1, _ = run_building_layer(fa, res, grid, A, B, model, cp)
        moved = [int(i) for i, c, c1 in zip(layer["building_id"], layer["class"], layer1["class"]) if c != c1]
        sb = _round(score_buildings(layer, fall, aoi=aoi))
        unobs = layer[layer["class"].isin(["unobserved", "not examined"])]
        status = dict(zip(fall["building_id"], fall["status"]))
        sb["unobserved"] = int(len(unobs))
        sb["unobserved_changed_in_truth"] = [
            int(i) for i in unobs["building_id"] if status.get(i, "unchanged") != "unchanged"
        ]
        sb["classes"] = {str(k): int(v) for k, v in layer["class"].value_counts().items()}
        sb["mistakes"] = layer_mistakes(layer, fall, aoi)
        # the footprint rule alone (the intermediate this script scored before the layer): a second column
        mk = res.changed_at(cfg.region_confidence)
        old = classify_buildings(
            fa,
            mk,
            res.dz_m,
            grid,
            params=cfg.buildings,
            z_a=za,
            z_b=zb,
            confidence=res.confidence,
            id_field="building_id",
            confidence_level=cfg.region_confidence,
            min_part_cells=res.min_region_cells,
        )
        out[mode] = {
            "cells": cells,
            "buildings": sb,
            "buildings_footprint_rule": _round(score_buildings(old, fall, aoi=aoi)),
            "buildings_changed_part_on": _round(score_buildings(layer1, fall, aoi=aoi)),
            "classes_moved_by_changed_part": moved,
            "min_region_cells": res.min_region_cells,
        }
        if mode == "region" and run_layer is not None:
            a = dict(zip(layer["building_id"], layer["class"]))
            b = dict(zip(run_layer["building_id"], run_layer["class"]))
            out[mode]["same_classes_as_run"] = a == b
    out["seconds"] = round(time.perf_counter() - t, 1)
    return out


def probchange(scene: Path, params=None) -> dict:
    from geocd.change.metrics import binary_scores
    from geocd.io.raster import read_band
    from geocd.io.manifest import load_manifest
    from geocd.probchange import ProbChangeParams, run_probchange

    m = load_manifest(scene)
    sats = set(m.truth.get("satellite_images") or [])
    eps = tuple(
        dataclasses.replace(e, images=tuple(i for i in e.images if not sats or i.name in sats)) for e in m.epochs
    )
    m = dataclasses.replace(m, epochs=eps)
    truth, _ = read_band(scene / "truth" / "change_mask.tif")
    t = time.perf_counter()
    r = run_probchange(m, variant="objectspace", params=params or ProbChangeParams.robust(), write=False)["result"]
    s = _round(binary_scores(r.changed(), truth > 0))
    s["seconds"] = round(time.perf_counter() - t, 1)
    return s


def volume(path: Path) -> dict:
    res = json.loads(path.read_text())
    pooled = res["change_pooled"]
    return {
        k: {"auc": round(v["auc"], 4), "auc_agg9": round(v.get("auc_agg9", float("nan")), 4)} for k, v in pooled.items()
    }


def markdown(results: dict, tuned: dict) -> str:
    names = list(results)
    lines = [
        "| figure | " + " | ".join(f"{n}{' *' if tuned.get(n) else ''}" for n in names) + " |",
        "|---|" + "---|" * len(names),
    ]

    def row(label, fn):
        vals = []
        for n in names:
            try:
                vals.append(fn(results[n]))
            except (KeyError, TypeError):
                vals.append("–")
        lines.append(f"| {label} | " + " | ".join(vals) + " |")

    row(
        "buildings F1 of the building layer, epoch-A footprints (tp/fp/fn; unobserved)",
        lambda r: "{f1:.3f} ({tp}/{fp}/{fn}; {unobserved})".format(**r["sc"]["region"]["buildings"]),
    )
    row(
        "same, SRI per-cell test",
        lambda r: "{f1:.3f} ({tp}/{fp}/{fn}; {unobserved})".format(**r["sc"]["cell"]["buildings"]),
    )
    for lev in ("90", "95", "99"):
        row(
            f"cells {lev} %: P / R / F1 / false alarms",
            lambda r, lev=lev: "{precision:.3f} / {recall:.3f} / **{f1:.3f}** / {fa:.2f} %".format(
                fa=100 * r["sc"]["region"]["cells"][lev]["false_alarm_rate"], **r["sc"]["region"]["cells"][lev]
            ),
        )
    for lev in ("90", "95", "99"):
        row(
            f"cells {lev} %, SRI per-cell test",
            lambda r, lev=lev: "{precision:.3f} / {recall:.3f} / {f1:.3f} / {fa:.2f} %".format(
                fa=100 * r["sc"]["cell"]["cells"][lev]["false_alarm_rate"], **r["sc"]["cell"]["cells"][lev]
            ),
        )
    row(
        "probchange F1 (robust, object space; P / R)",
        lambda r: "{f1:.3f} ({precision:.2f} / {recall:.2f})".format(**r["probchange"]),
    )
    for key, label in (
        ("3-D octree (relit)", "octree per-pixel AUC (eq. 27, relit)"),
        ("3-D octree 3×3 (relit)", "octree 3×3 per-pixel AUC"),
        ("2-D Carlotto joint histogram", "Carlotto per-pixel AUC"),
        ("2-D DEM warp + difference", "DEM warp + difference per-pixel AUC"),
    ):
        row(label, lambda r, key=key: f"{r['volume'][key]['auc']:.3f}")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", action="append", default=[], help="NAME=SCENE[:RUN_DIR]")
    ap.add_argument("--volume", action="append", default=[], help="NAME=volume_results.json")
    ap.add_argument("--tuned", action="append", default=[], help="NAME of a scene used to choose parameters")
    ap.add_argument("--no-probchange", action="store_true")
    ap.add_argument(
        "--volume-only",
        action="store_true",
        help="only replace the octree figures (from --volume) in the --json of an earlier run",
    )
    ap.add_argument("--json", default=None)
    ap.add_argument("--markdown", default=None)
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    prev = json.loads(Path(args.json).read_text()) if args.json and Path(args.json).is_file() else {}
    results: dict = prev.get("scenes", {})
    vols = dict(v.split("=", 1) for v in args.volume)
    prev_cmd = prev.get("command")
    if prev_cmd:  # the figures this run does not replace (octree, probchange) keep their command
        prev.setdefault("earlier_commands", []).append(prev_cmd)
    for spec in [] if args.volume_only else args.scene:
        name, rest = spec.split("=", 1)
        scene, _, run = rest.partition(":")
        scene_p = (REPO / scene) if not Path(scene).is_absolute() else Path(scene)
        r = results.setdefault(name, {})
        r["scene"] = scene
        print(f"== {name}", flush=True)
        r["sc"] = self_consistency(scene_p, Path(run) if run else None)
        print(json.dumps({k: r["sc"][k]["cells"]["99"] for k in ("region", "cell")}), flush=True)
        if not args.no_probchange:
            r["probchange"] = probchange(scene_p)
            print("probchange", r["probchange"], flush=True)
        if name in vols:
            r["volume"] = volume(Path(vols[name]))
    for name, p in vols.items():
        if name in results:
            results[name]["volume"] = volume(Path(p))
    tuned = {n: (n in args.tuned) for n in results}
    doc = {
        **{k: v for k, v in prev.items() if k not in ("command", "scenes", "tuned_on")},
        "command": " ".join(sys.argv),
        "scenes": results,
        "tuned_on": [n for n, t in tuned.items() if t],
    }
    if args.json:
        Path(args.json).write_text(json.dumps(doc, indent=1, default=float))
    md = markdown(results, tuned)
    print(md)
    if args.markdown:
        Path(args.markdown).write_text(md)


if __name__ == "__main__":
    main()
