"""Transfer of a self-consistency model between generated towns: the model as learned vs calibrated to the pair.

A model is learned on one town's epoch-A pair-DEMs (``--source RUN``, a ``geocd run`` output folder) and applied
to other towns' runs (``--target NAME=SCENE:RUN``, the scene folder for its truth), once with one satellite pair
per epoch (as in the Kahramanmaraş case) and once with all pairs, with ``calibration="none"`` and ``"pair"``.
Cells at 99 % (region test) are scored against the town's truth change mask (P / R / F1 / false alarms among the
cells without 3-D change). Usage::

    .venv/bin/python bench/eval_transfer_towns.py --source R1 --target town_seed3=T3:R3 --target town_seed2_sun=T2:R2 \\
        [--json bench/results/transfer_towns.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _load(run: Path) -> dict:
    from geocd.stereo import read_pair_dem

    by: dict = {}
    for f in sorted((run / "stereo").rglob("*.tif")):
        p = read_pair_dem(f)
        by.setdefault(p.epoch, []).append(p)
    return by


def main(argv=None) -> int:
    from geocd.change.metrics import binary_scores
    from geocd.consistency import ChangeParams, ConsistencyParams, change_test, learn_self_consistency
    from geocd.io.manifest import load_manifest
    from geocd.io.raster import read_on_grid

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", required=True, help="geocd run folder of the town the model is learned on (epoch A)")
    ap.add_argument("--target", action="append", required=True, help="NAME=SCENE:RUN")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    model = learn_self_consistency([_load(Path(args.source))["A"]], ConsistencyParams())
    out: dict = {"source": args.source, "reference_law": model.reference_law, "results": {}}
    for t in args.target:
        name, _, rest = t.partition("=")
        scene, _, run = rest.partition(":")
        by = _load(Path(run))
        grid = by["A"][0].grid
        truth = read_on_grid(load_manifest(scene).truth_path("change_mask"), grid) > 0.5
        sets = {
            "one satellite pair per epoch": (
                [p for p in by["A"] if p.name == "A_sat1__A_sat2"],
                [p for p in by["B"] if p.name == "B_sat1__B_sat2"],
            ),
            "all pairs": (by["A"], by["B"]),
        }
        for sname, (A, B) in sets.items():
            for cal in ("none", "pair"):
                res = change_test(A, B, model, ChangeParams(calibration=cal))
                s = binary_scores(np.isin(res.changed_at(99.0), (1, -1)), truth, res.observed)
                r = {k: round(float(s[k]), 4) for k in ("precision", "recall", "f1", "false_alarm_rate")}
                r["calibration"] = res.calibration.to_dict() if res.calibration is not None else None
                out["results"][f"{name} | {sname} | {cal}"] = r
                print(name, "|", sname, "|", cal, json.dumps(r), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
