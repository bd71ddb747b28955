"""Sensitivity of the change test's constants on several towns (docs/towns.md, "Constants").

For each scene (``NAME=SCENE:RUN_DIR`` as in ``bench/eval_towns.py``), with everything else at ``geocd run``'s
defaults:

* the region test's cluster-forming level (90 / 95 / 99 %): cells F1 and buildings F1 at 99 %;
* the minimum mapping unit of the per-cell test: 4 cells (the former constant) against one matching window;
* the building rule ``min_changed``: the largest changed fraction among truly unchanged footprints and the
  smallest among truly changed ones (any ``min_changed`` between them gives the same classes);
* with ``--probchange P1,P2``: probchange's ``no_depth_prior`` π∅ at these values (robust model, object space,
  satellite views): pixel F1.

Buildings are those of the building layer ``geocd run`` writes (:func:`geocd.pipeline.run_building_layer`,
the manifest's epoch-A footprints, new buildings detected in the change map), scored as in
``bench/eval_towns.py`` (:func:`geocd.change.buildings.score_buildings`: collapsed / partly collapsed /
lowered / raised / new count as changed; unchanged and unobserved as not changed; ``unobserved`` is their count).

Usage::

    .venv/bin/python bench/eval_constants.py --scene sample_aoi=sample_aoi:/tmp/run0 ... --json bench/results/towns_constants.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))


def run_scene(scene: Path, run_dir: Path | None) -> dict:
    from shapely.geometry import box

    from eval_towns import _pairs, _round
    from geocd.change.buildings import score_buildings
    from geocd.change.metrics import binary_scores
    from geocd.consistency import ChangeParams, change_test, learn_self_consistency
    from geocd.io.raster import read_on_grid
    from geocd.io.vector import read_footprints
    from geocd.pipeline import RunConfig, run_building_layer

    m, by = _pairs(scene, run_dir)
    A, B = by["A"], by["B"]
    grid = A[0].grid
    truth = read_on_grid(m.truth_path("change_mask"), grid) > 0.5
    fa = read_footprints(m.footprints.path, crs=grid.crs, layer=m.footprints.layer)  # as geocd run: epoch A's
    fall = read_footprints(m.truth_path("footprints_all"), crs=grid.crs)
    status = dict(zip(fall["building_id"], fall["status"]))
    cfg = RunConfig()

    def figures(res, model, level=99.0):
        mk = res.changed_at(level)
        cells = _round(binary_scores((mk == 1) | (mk == -1), truth, res.observed))
        b, _ = run_building_layer(fa, res, grid, A, B, model, cfg)  # the layer geocd run writes
        sb = _round(score_buildings(b, fall, aoi=box(*grid.bounds)))
        fp = b[(b["source"] == "footprints") & ~b["class"].isin(["unobserved", "not examined"])]
        changed = np.array([status.get(i) not in (None, "unchanged") for i in fp["building_id"]])
        fr = fp["frac_changed"].to_numpy(float)
        margins = {
            "max_frac_unchanged": round(float(fr[~changed].max()), 4) if (~changed).any() else None,
            "min_frac_changed": round(float(fr[changed].min()), 4) if changed.any() else None,
        }
        return {
            "cells_f1": cells["f1"],
            "cells_false_alarms": cells["false_alarm_rate"],
            "buildings_f1": sb["f1"],
            "buildings": [sb["tp"], sb["fp"], sb["fn"]],
            "unobserved": int(b["class"].isin(["unobserved", "not examined"]).sum()),
            **margins,
        }

    out: dict = {"cluster_confidence": {}, "per_cell_mapping_unit": {}}
    for cc in (90.0, 95.0, 99.0):
        model = learn_self_consistency([A, B], dataclasses.replace(cfg.consistency, cluster_confidence=cc))
        out["cluster_confidence"][f"{cc:g}"] = figures(change_test(A, B, model, cfg.change), model)
        if cc == cfg.consistency.cluster_confidence:
            base = model
    for mmu in (4, None):
        res = change_test(A, B, base, ChangeParams(significance="cell", min_region_cells=mmu))
        out["per_cell_mapping_unit"][str(res.min_region_cells)] = figures(res, base)
    return out


def probchange_prior(scene: Path, values: list[float]) -> dict:
    from eval_towns import probchange

    from geocd.probchange import ProbChangeParams

    return {f"{v:g}": probchange(scene, ProbChangeParams.robust(no_depth_prior=v)) for v in values}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", action="append", required=True, help="NAME=SCENE[:RUN_DIR]")
    ap.add_argument("--json", default=None)
    ap.add_argument("--probchange", default=None, help="comma-separated no_depth_prior values to test")
    ap.add_argument("--no-sc", action="store_true", help="skip the self-consistency constants")
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    res = {}
    for spec in args.scene:
        name, rest = spec.split("=", 1)
        scene, _, run = rest.partition(":")
        scene_p = (REPO / scene) if not Path(scene).is_absolute() else Path(scene)
        res[name] = {} if args.no_sc else run_scene(scene_p, Path(run) if run else None)
        if args.probchange:
            res[name]["probchange_no_depth_prior"] = probchange_prior(
                scene_p, [float(v) for v in args.probchange.split(",")]
            )
        print(name, json.dumps(res[name]), flush=True)
    if args.json:
        prev = json.loads(Path(args.json).read_text()) if Path(args.json).is_file() else {"scenes": {}}
        for k, v in res.items():
            prev["scenes"].setdefault(k, {}).update(v)
        prev.setdefault("commands", []).append(" ".join(sys.argv))
        Path(args.json).write_text(json.dumps(prev, indent=1))


if __name__ == "__main__":
    main()
