"""Self-consistency of a real tri-stereo set (issue 5): the s2p Pléiades Marseille triplet.

Three images of one date give three pair-DEMs and three comparisons of a static scene. The script

* learns the self-consistency curves from the three comparisons and prints them (bin counts included);
* counts, for each comparison, the fraction of common cells whose |Δ̃| exceeds the curve at s% —
  in-sample (should be ≈ 1 − s by construction) and leave-one-out (curves learned on the two other
  comparisons: an honest check that the curves transfer);
* writes the scatter + curves plot.

Usage::

    .venv/bin/geocd --progress none stereo TRIPLET_MANIFEST --out OUT      # pair-DEMs in OUT/stereo/<epoch>/
    .venv/bin/python bench/eval_triplet_consistency.py OUT/stereo [--plot docs/sc_marseille_scatter.png]

A manifest for the triplet (paths into ../shared/data/s2p_pleiades/input_triplet) is written by
``--write-manifest DIR``.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

MANIFEST = """geocd_manifest: 1
name: s2p_marseille_triplet
scene_class: urban
output: out
epochs:
  - name: T
    date: 2013-04-17
    sensor: Pleiades pan 0.5 m
    images:
      - {d}/img_01.tif
      - {d}/img_02.tif
      - {d}/img_03.tif
"""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("stereo_dir", nargs="?")
    ap.add_argument("--plot", default=None)
    ap.add_argument("--write-manifest", default=None)
    args = ap.parse_args()
    if args.write_manifest:
        d = Path(args.write_manifest)
        d.mkdir(parents=True, exist_ok=True)
        src = (REPO.parent / "shared" / "data" / "s2p_pleiades" / "input_triplet").resolve()
        (d / "scene.yaml").write_text(MANIFEST.format(d=src))
        print(f"wrote {d / 'scene.yaml'}")
        return

    from geocd.change.plots import plot_scatter_curves
    from geocd.consistency import ConsistencyParams, align_reconstructions, learn_self_consistency, match_pairs
    from geocd.stereo import read_pair_dem

    raw = [read_pair_dem(p) for p in sorted(Path(args.stereo_dir).rglob("*.tif"))]
    print("pair-DEMs:", ", ".join(f"{p.name} (valid {100 * p.completeness:.1f}%)" for p in raw))
    # one vertical reference for all three (RPC biases shift each pair-DEM by a constant)
    pairs, offsets = align_reconstructions(raw)
    print("vertical offsets removed (m):", ", ".join(f"{k} {v:+.2f}" for k, v in offsets.items()))
    levels = (90.0, 95.0, 99.0)
    params = ConsistencyParams(confidences=levels, align="none")  # already aligned
    model = learn_self_consistency(
        [pairs], params, provenance={"scene": "s2p Marseille triplet", "scene_class": "urban"}
    )
    t = model.curves_table()
    print("\nself-consistency curves (|Δ̃| in pixels of disparity) per score bin")
    print(
        t[["score_lo", "score_hi", "n_pairs", "q90", "q95", "q99"]].to_string(
            index=False, float_format=lambda v: f"{v:.3f}"
        )
    )
    comps = list(itertools.combinations(pairs, 2))
    print("\nfraction of common cells flagged as change (|Δ̃| above the s% curve), same-date comparisons")
    print(
        f"{'comparison':34s} {'cells':>8s} "
        + " ".join(f"{'in ' + str(int(s)) + '%':>8s} {'LOO ' + str(int(s)) + '%':>8s}" for s in levels)
    )
    for k, (p, q) in enumerate(comps):
        dt, sc, _, both = match_pairs(p, q)
        others = [c for j, c in enumerate(comps) if j != k]
        # leave-one-out model: learned from the other two comparisons only
        loo = learn_self_consistency([[a, b] for a, b in others], params)
        cells = []
        for s in levels:
            f_in = float(np.mean(np.abs(dt[both]) > model.threshold(sc[both], s)))
            f_loo = float(np.mean(np.abs(dt[both]) > loo.threshold(sc[both], s)))
            cells.append(f"{100 * f_in:7.2f}% {100 * f_loo:7.2f}%")
        print(f"{p.name + ' vs ' + q.name:34s} {int(both.sum()):8d} " + " ".join(cells))
    print("expected ≈ " + ", ".join(f"{100 - s:g}%" for s in levels))
    if args.plot:
        plot_scatter_curves(model, args.plot, title="s2p Marseille triplet (Pléiades, 3 pairs)")
        print(f"plot: {args.plot}")


if __name__ == "__main__":
    main()
