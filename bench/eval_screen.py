"""The thesis's Table 4.1 redone: F1 of the 2-D screen per grid feature and layer, superpixels, misregistration.

Data:
* ``sample_aoi`` — the cross-epoch pair and the within-epoch no-change pair that ``geocd screen`` picks
  (views projected on the terrain DEM: the raw views over the AOI grid, as the tiered run uses them),
  scored against the truth on the AOI grid: "2-D/3-D object change" = 3-D change (truth/change_mask)
  ∪ repainted roofs (non3d_mask = 1); the season (non3d_mask = 2) and the sun are not changes.
  Also scored against the 3-D change alone.
* the five LEVIR-CD pairs (``../shared/data/levircd_building_change_samples``), label = new or
  demolished buildings; train_386 has no change (the control pair).

Threshold rules (a threshold picked on the pair it is scored on is not a result — the "oracle" column
is the thesis's own rule, best F1 on the evaluation data, shown only to compare with its Table 4.1):
* ``nochange`` — geocd's rule: the 99 % quantile of the dissimilarities of a no-change pair (sample_aoi:
  the within-epoch pair; LEVIR: train_386, scored on the other four), then Otsu's split of the scored
  pair's values above it (``nochange_quantile``: the bare quantile);
* ``labelled`` — LEVIR only, leave one pair out: best pooled F1 on the other labelled pairs;
* ``oracle`` — best F1 on the scored pairs themselves (upper bound, as in the thesis).

Usage::

    nice -n 10 .venv/bin/python bench/eval_screen.py --views /tmp/screen_views --out bench/results/screen_table.json
    # --quick: fewer features (CI-sized); --sets levir,sample_aoi

``--views`` is a folder holding the sample_aoi views on the grid (made by ``geocd screen sample_aoi --out``
DIR: DIR/views/*.tif); made there when missing.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from geocd.screen.cnn import random_state_dict  # noqa: E402
from geocd.screen.core import (
    cell_distance,
    cell_valid,
    normalise_image,
    segment_mean,
    shadow_mask,  # noqa: E402
    shift_image,
    spread_to_pixels,
    superpixels,
    vegetation_mask,
)
from geocd.screen.features import FeatureSpec, grey  # noqa: E402
from geocd.screen.threshold import NullDistribution, f1_curve, f1_scores, split_above, threshold_best_f1  # noqa: E402

LEVIR = ROOT.parent / "shared" / "data" / "levircd_building_change_samples"
SHIFTS = (0, 2, 4)
SUPERPIXELS = ("felzenszwalb", "slic", "none")


def feature_specs(
    quick: bool, weights_dir: Path, weights: dict[str, str] | None = None
) -> list[tuple[str, FeatureSpec]]:
    """(label, spec) of every row of the table; CNN rows use random-init (He) weights the script makes, or the
    weights file named for that backbone in ``weights`` ({"vgg19": "vgg19.npz"}: e.g. trained ImageNet weights)."""
    specs = []
    cells = (16,) if quick else (16, 32)
    for kind in ("patch", "daisy", "randbank"):
        for c in cells:
            specs.append((f"{kind} {c}px", FeatureSpec(kind=kind, cell_px=c)))
    weights_dir.mkdir(parents=True, exist_ok=True)
    for bb, layers in (
        ("vgg19", ("pool2", "pool3", "pool4", "pool5") if not quick else ("pool4",)),
        ("resnet18", ("layer2", "layer3") if not quick else ()),
        ("efficientnet_lite0", ("stage3", "stage5", "stage6", "head") if not quick else ()),
    ):
        if not layers:
            continue
        if weights and bb in weights:
            w, tag = Path(weights[bb]), Path(weights[bb]).name
        else:
            w, tag = weights_dir / f"{bb}_random_init_seed0.npz", "random init"
            if not w.exists():
                np.savez(w, **random_state_dict(bb, seed=0))
        for ly in layers:
            specs.append((f"{bb} {ly} ({tag})", FeatureSpec(kind="cnn", backbone=bb, weights=str(w), layer=ly)))
    return specs


# ---------------------------------------------------------------------------------------------
def load_levir() -> list[dict]:
    from PIL import Image

    out = []
    for f in sorted(os.listdir(LEVIR / "A")):
        a = np.asarray(Image.open(LEVIR / "A" / f).convert("RGB")).transpose(2, 0, 1)
        b = np.asarray(Image.open(LEVIR / "B" / f).convert("RGB")).transpose(2, 0, 1)
        t = np.asarray(Image.open(LEVIR / "label" / f)) > 0
        if t.ndim == 3:
            t = t[..., 0]
        out.append({"name": f.split(".")[0], "a": a, "b": b, "truth": t, "names": ("red", "green", "blue")})
    return out


def load_sample_aoi(views: Path) -> dict:
    from geocd.io.raster import read_image, read_on_grid
    from geocd.geodesy import AOIGrid
    import rasterio

    summ = json.loads((views / "screen_summary.json").read_text())
    pa, pb = summ["pair"]
    nc = summ["nochange_pair"]
    ea, eb = summ["epoch_a"], summ["epoch_b"]
    e_nc = ea if nc[0].startswith(ea) else eb

    def img(p):
        im = read_image(p)
        d = im.data.astype(np.float32)
        d[:, ~im.valid] = np.nan
        return d

    a = img(views / "views" / f"{ea}_{pa}.tif")
    b = img(views / "views" / f"{eb}_{pb}.tif")
    c = img(views / "views" / f"{e_nc}_{nc[0]}.tif")
    d = img(views / "views" / f"{e_nc}_{nc[1]}.tif")
    with rasterio.open(views / "views" / f"{ea}_{pa}.tif") as ds:
        grid = AOIGrid.from_raster(ds)
    t3 = np.nan_to_num(read_on_grid(ROOT / "sample_aoi/truth/change_mask.tif", grid)) > 0
    n3 = np.nan_to_num(read_on_grid(ROOT / "sample_aoi/truth/non3d_mask.tif", grid))
    return {
        "name": "sample_aoi",
        "a": a,
        "b": b,
        "nc_a": c,
        "nc_b": d,
        "truth": t3 | (n3 == 1),
        "truth3d": t3,
        "pair": [pa, pb],
        "nochange_pair": nc,
        "grid": grid,
    }


# ---------------------------------------------------------------------------------------------
class PairCache:
    """Normalised images, superpixels and masks of one pair (reused across features)."""

    def __init__(self, a, b, gsd_m: float, names=None):
        self.na, self.va = normalise_image(a)
        self.nb, self.vb = normalise_image(b)
        self.names = names
        self.gsd = gsd_m
        self.valid = self.va & self.vb
        self._sp: dict = {}
        ga = vegetation_mask(self.na, self.va, names)
        gb = vegetation_mask(self.nb, self.vb, names)
        veg = (ga & gb) if ga is not None and gb is not None else np.zeros(self.valid.shape, bool)
        sh = shadow_mask(self.na, self.va) & shadow_mask(self.nb, self.vb)
        self.excl = veg | sh

    def labels(self, method: str):
        if method not in self._sp:
            self._sp[method] = (
                superpixels(self.na, method, self.gsd, 3.0),
                superpixels(self.nb, method, self.gsd, 3.0),
            )
        return self._sp[method]


def d_cells_for(feat, cache: PairCache, shift_px: float, fb_cache: dict) -> np.ndarray:
    a = cache.na if cache.na.shape[0] == cache.nb.shape[0] else grey(cache.na)[None]
    b = cache.nb if cache.na.shape[0] == cache.nb.shape[0] else grey(cache.nb)[None]
    if shift_px:
        b = shift_image(b, shift_px)
    xa = fb_cache.get("xa")
    if xa is None:
        xa = fb_cache["xa"] = feat.extract(a)
    xb = feat.extract(b)
    dc = cell_distance(xa, xb)
    return np.where(cell_valid(cache.valid, feat.cell_px, 0.5), dc, np.nan)


def final_d(dc: np.ndarray, cell: int, cache: PairCache, sp: str, exclude: bool = True) -> np.ndarray:
    H, W = cache.valid.shape
    dp = np.where(cache.valid, spread_to_pixels(dc, (H, W), cell), np.nan)
    if sp != "none":
        la, lb = cache.labels(sp)
        with np.errstate(invalid="ignore"):
            dp = np.fmax(segment_mean(dp, la), segment_mean(dp, lb))
        dp = np.where(cache.valid, dp, np.nan)
    if exclude:
        dp = np.where(cache.excl & np.isfinite(dp), 0.0, dp)
    return dp.astype(np.float32)


def oracle(ds, ts):
    return threshold_best_f1(ds, ts)


def pooled_f1(ds, ts, t):
    return float(f1_curve(ds, ts, np.array([t]))[0])


# ---------------------------------------------------------------------------------------------
def eval_levir(specs, sps, shifts, log) -> list[dict]:
    pairs = load_levir()
    caches = [PairCache(p["a"], p["b"], 0.5, p["names"]) for p in pairs]
    ctrl = [i for i, p in enumerate(pairs) if not p["truth"].any()]
    scored = [i for i, p in enumerate(pairs) if p["truth"].any()]
    rows = []
    for label, spec in specs:
        t0 = time.perf_counter()
        feat = spec.build()
        fcache = [dict() for _ in pairs]
        for sh in shifts:
            dcs = [d_cells_for(feat, c, sh, fc) for c, fc in zip(caches, fcache)]
            for sp in sps:
                ds = [final_d(dc, feat.cell_px, c, sp) for dc, c in zip(dcs, caches)]
                # the no-change threshold comes from the control pair in its own registration (shift 0)
                if sh == 0:
                    null_key = (label, sp)
                    NULLS[null_key] = NullDistribution.from_values(ds[ctrl[0]], pairs[ctrl[0]]["name"])
                null = NULLS[(label, sp)]
                t_q = null.threshold(1.0)
                f_q = pooled_f1([ds[i] for i in scored], [pairs[i]["truth"] for i in scored], t_q)
                # the rule geocd uses: the quantile, then Otsu's split of each screened pair's values above it
                tp = fp = fn = 0
                per_pair_nc, t_split = {}, []
                for i in scored:
                    t_i = split_above(ds[i], t_q)
                    sc = f1_scores(ds[i] > t_i, pairs[i]["truth"], np.isfinite(ds[i]))
                    tp, fp, fn = tp + sc["tp"], fp + sc["fp"], fn + sc["fn"]
                    per_pair_nc[pairs[i]["name"]] = sc["f1"]
                    t_split.append(round(t_i, 3))
                f_nc = 2 * tp / max(2 * tp + fp + fn, 1)
                # leave one labelled pair out
                tp = fp = fn = 0
                for i in scored:
                    others = [j for j in scored if j != i]
                    t_l, _ = threshold_best_f1([ds[j] for j in others], [pairs[j]["truth"] for j in others])
                    s = f1_scores(ds[i] > t_l, pairs[i]["truth"], np.isfinite(ds[i]))
                    tp, fp, fn = tp + s["tp"], fp + s["fp"], fn + s["fn"]
                f_loo = 2 * tp / max(2 * tp + fp + fn, 1)
                t_or, f_or = oracle([ds[i] for i in scored], [pairs[i]["truth"] for i in scored])
                dctl = ds[ctrl[0]][np.isfinite(ds[ctrl[0]])]
                ctrl_fa = float(np.mean(dctl > split_above(dctl, t_q)))
                rows.append(
                    {
                        "set": "levir",
                        "feature": label,
                        "cell_px": feat.cell_px,
                        "superpixels": sp,
                        "shift_px": sh,
                        "f1_nochange": round(f_nc, 3),
                        "t_nochange_split": t_split,
                        "f1_nochange_quantile": round(f_q, 3),
                        "t_nochange_quantile": round(t_q, 3),
                        "f1_labelled_loo": round(f_loo, 3),
                        "f1_oracle": round(f_or, 3),
                        "t_oracle": round(t_or, 3),
                        "per_pair_f1_nochange": per_pair_nc,
                        "control_false_alarm": round(ctrl_fa, 4),
                    }
                )
                log(rows[-1])
        print(f"  {label}: {time.perf_counter() - t0:.1f} s", flush=True)
    return rows


def eval_sample(specs, sps, shifts, views: Path, log) -> list[dict]:
    s = load_sample_aoi(views)
    gsd = s["grid"].posting_m
    pc = PairCache(s["a"], s["b"], gsd)
    nc = PairCache(s["nc_a"], s["nc_b"], gsd)
    rows = []
    for label, spec in specs:
        t0 = time.perf_counter()
        feat = spec.build()
        fc, fn_ = {}, {}
        dnc = d_cells_for(feat, nc, 0, fn_)
        for sh in shifts:
            dc = d_cells_for(feat, pc, sh, fc)
            for sp in sps:
                d = final_d(dc, feat.cell_px, pc, sp)
                null = NullDistribution.from_values(final_d(dnc, feat.cell_px, nc, sp), "within-epoch pair")
                t_q = null.threshold(1.0)
                t_nc = split_above(d, t_q)
                ok = np.isfinite(d)
                r = {
                    "set": "sample_aoi",
                    "feature": label,
                    "cell_px": feat.cell_px,
                    "superpixels": sp,
                    "shift_px": sh,
                    "t_nochange_quantile": round(t_q, 3),
                    "t_nochange": round(t_nc, 3),
                    "changed_fraction": round(float(np.mean(d[ok] > t_nc)), 4),
                }
                for key, tr in (("", s["truth"]), ("_3d", s["truth3d"])):
                    r[f"f1_nochange_quantile{key}"] = f1_scores(d > t_q, tr, ok)["f1"]
                    sc = f1_scores(d > t_nc, tr, ok)
                    t_or, f_or = oracle([d], [tr])
                    r.update(
                        {
                            f"f1_nochange{key}": sc["f1"],
                            f"precision_nochange{key}": sc["precision"],
                            f"recall_nochange{key}": sc["recall"],
                            f"f1_oracle{key}": round(f_or, 3),
                            f"t_oracle{key}": round(t_or, 3),
                        }
                    )
                rows.append(r)
                log(r)
        print(f"  {label}: {time.perf_counter() - t0:.1f} s", flush=True)
    return rows


NULLS: dict = {}


def render(doc: dict) -> str:
    """The tables of docs/screen.md from the JSON."""
    rows = doc["rows"]
    feats = list(dict.fromkeys(r["feature"] for r in rows))

    def get(st, f, sp="felzenszwalb", sh=0):
        return next(
            (
                r
                for r in rows
                if r["set"] == st and r["feature"] == f and r["superpixels"] == sp and r["shift_px"] == sh
            ),
            None,
        )

    out = [
        "**LEVIR-CD, 4 changed pairs (train_386 = the no-change control), Felzenszwalb, no shift** — pooled pixel F1",
        "",
        "| feature | no-change rule (t per pair) | bare 99 % quantile | labelled, leave one out | oracle (t) | "
        "control false alarms |",
        "|---|---|---|---|---|---|",
    ]
    for f in feats:
        r = get("levir", f)
        if r:
            ts = r.get("t_nochange_split", [])
            out.append(
                f"| {f} | {r['f1_nochange']:.3f} ({min(ts):.2f}–{max(ts):.2f}) | {r['f1_nochange_quantile']:.3f} "
                f"| {r['f1_labelled_loo']:.3f} | {r['f1_oracle']:.3f} ({r['t_oracle']:.2f}) | "
                f"{100 * r['control_false_alarm']:.1f} % |"
            )
    out += [
        "",
        "**sample_aoi, A_sat1 → B_sat1 on the terrain DEM, threshold from B_sat1/B_sat2, Felzenszwalb, no "
        "shift** — pixel F1 against 2-D/3-D object change (3-D change ∪ repainted roofs) and 3-D change alone",
        "",
        "| feature | F1 (P / R) | t | F1 3-D | bare quantile F1 | oracle F1 (t) | oracle F1 3-D | changed |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for f in feats:
        r = get("sample_aoi", f)
        if r:
            out.append(
                f"| {f} | {r['f1_nochange']:.3f} ({r['precision_nochange']:.2f} / {r['recall_nochange']:.2f}) | "
                f"{r['t_nochange']:.2f} | {r['f1_nochange_3d']:.3f} | {r['f1_nochange_quantile']:.3f} | "
                f"{r['f1_oracle']:.3f} ({r['t_oracle']:.2f}) | {r['f1_oracle_3d']:.3f} | "
                f"{100 * r['changed_fraction']:.1f} % |"
            )
    out += [
        "",
        "**Superpixels** (no shift): LEVIR labelled leave-one-out F1 / sample_aoi no-change-rule F1",
        "",
        "| feature | Felzenszwalb | SLIC | none |",
        "|---|---|---|---|",
    ]
    for f in feats:
        cells = []
        for sp in SUPERPIXELS:
            a, b = get("levir", f, sp), get("sample_aoi", f, sp)
            cells.append(
                f"{a['f1_labelled_loo']:.3f} / {b['f1_nochange']:.3f}"
                if a and b
                else (f"{a['f1_labelled_loo']:.3f} / –" if a else "–")
            )
        out.append(f"| {f} | " + " | ".join(cells) + " |")
    out += [
        "",
        "**Misregistration** (B shifted by 0 / 2 / 4 px at 30°, Felzenszwalb): LEVIR labelled "
        "leave-one-out F1; sample_aoi no-change-rule F1 (the threshold and the null pair unshifted)",
        "",
        "| feature | LEVIR 0 | 2 | 4 | sample_aoi 0 | 2 | 4 |",
        "|---|---|---|---|---|---|---|",
    ]
    for f in feats:
        cells = []
        for st, key in (("levir", "f1_labelled_loo"), ("sample_aoi", "f1_nochange")):
            for sh in SHIFTS:
                r = get(st, f, "felzenszwalb", sh)
                cells.append(f"{r[key]:.3f}" if r else "–")
        out.append(f"| {f} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=Path, default=Path("/tmp/screen_views"))
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "screen_table.json")
    ap.add_argument("--sets", default="levir,sample_aoi")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--features", default=None, help="comma-separated labels to run (default all)")
    ap.add_argument("--markdown", action="store_true", help="print the tables of --out and stop")
    ap.add_argument(
        "--weights",
        action="append",
        default=[],
        metavar="BACKBONE=FILE",
        help="weights for the vgg19 / resnet18 / efficientnet_lite0 rows (e.g. trained ones) instead of random init",
    )
    a = ap.parse_args(argv)
    if a.markdown:
        print(render(json.loads(a.out.read_text())))
        return 0
    specs = feature_specs(a.quick, a.views / "weights", dict(w.split("=", 1) for w in a.weights))
    if a.features:
        keep = a.features.split(",")
        specs = [s for s in specs if any(s[0].startswith(k) for k in keep)]
    sps = SUPERPIXELS
    shifts = SHIFTS
    rows = []
    old = json.loads(a.out.read_text()) if a.out.exists() else {"rows": []}

    def log(r):
        print(json.dumps({k: v for k, v in r.items() if k != "per_pair_f1_nochange"}), flush=True)

    t0 = time.perf_counter()
    sets = a.sets.split(",")
    if "levir" in sets:
        if not LEVIR.exists():
            print(f"skipping LEVIR-CD: {LEVIR} absent")
        else:
            rows += eval_levir(specs, sps, shifts, log)
    if "sample_aoi" in sets:
        if not (a.views / "screen_summary.json").exists():
            from geocd.screen.pipeline import run_screen_manifest

            run_screen_manifest(ROOT / "sample_aoi", out=a.views)
        rows += eval_sample(specs, sps, shifts, a.views, log)
    done = {(r["set"], r["feature"], r["superpixels"], r["shift_px"]) for r in rows}
    keep = [r for r in old.get("rows", []) if (r["set"], r["feature"], r["superpixels"], r["shift_px"]) not in done]
    res = {
        "command": "bench/eval_screen.py " + " ".join(argv or sys.argv[1:]),
        "seconds": round(time.perf_counter() - t0, 1),
        "rows": keep + rows,
    }
    a.out.write_text(json.dumps(res, indent=1))
    print(f"wrote {a.out} ({len(res['rows'])} rows) in {res['seconds']} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
