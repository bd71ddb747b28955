"""Figures and numbers of docs/ortho.md.

Usage (from the repository root)::

    .venv/bin/geocd --progress none ortho sample_aoi --out /tmp/ortho_run      # stereo DSMs + every ortho (~1–4 min)
    .venv/bin/python bench/figures/ortho_show.py /tmp/ortho_run

Writes ``bench/results/ortho_sample_aoi.json`` and ``docs/ortho_sample_aoi.png``: the orthos made on geocd stereo's
DSMs against the same views orthorectified on the truth DSMs, registration between views (RPC and frame),
and what a classic ortho puts on the cells a true ortho masks.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from geocd.io.cameras import load_camera  # noqa: E402
from geocd.io.raster import read_band, read_dem, read_image  # noqa: E402
from geocd.ortho import OCCLUDED, OrthoParams, orthorectify  # noqa: E402

AOI = REPO / "sample_aoi"


def shift_cells(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> float:
    """|translation| (cells) between two masked images: FFT cross-correlation, parabolic sub-cell peak."""
    a = np.where(m, a - a[m].mean(), 0)
    b = np.where(m, b - b[m].mean(), 0)
    c = np.fft.fftshift(np.real(np.fft.ifft2(np.fft.fft2(a) * np.conj(np.fft.fft2(b)))))
    i, j = np.unravel_index(np.argmax(c), c.shape)

    def par(lo, z, hi):
        return 0.5 * (lo - hi) / (lo - 2 * z + hi)

    return float(
        np.hypot(
            i + par(c[i - 1, j], c[i, j], c[i + 1, j]) - c.shape[0] // 2,
            j + par(c[i, j - 1], c[i, j], c[i, j + 1]) - c.shape[1] // 2,
        )
    )


def grey(values: np.ndarray) -> np.ndarray:
    return values.astype(np.float64).mean(axis=0)


def main(run: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out: dict = {"dsm": {}, "views": {}, "pairs": {}}
    for e in "AB":
        h, _ = read_band(run / "ortho" / e / f"dsm_{e}.tif", 1)
        filled, _ = read_band(run / "ortho" / e / f"dsm_{e}.tif", 2)
        t, _ = read_band(AOI / "truth" / f"dsm_{e}.tif")
        err = (h - t)[filled == 0]
        out["dsm"][e] = {
            "holes_filled": round(float(filled.mean()), 4),
            "median_abs_err_m": round(float(np.median(np.abs(err))), 3),
            "share_abs_err_gt_2m": round(float(np.mean(np.abs(err) > 2)), 4),
        }
    views = {
        "A": ["A_sat1", "A_sat2", "A_sat3", "A_sat4", "A_air1", "A_air2", "A_air3"],
        "B": ["B_sat1", "B_sat2", "B_sat3"],
    }
    truth_orthos = {}
    for e, names in views.items():
        d = read_dem(AOI / "truth" / f"dsm_{e}.tif")
        for n in names:
            p = AOI / "images" / f"{n}.tif"
            cam = load_camera(p, AOI / "images" / f"{n}.camera.json" if "air" in n else None)
            img = read_image(p)
            tr = orthorectify(img.data, cam, d.grid, d.height_m, valid=img.valid)
            truth_orthos[n] = tr
            with __import__("rasterio").open(run / "ortho" / e / f"{n}.tif") as ds:
                st_vals = ds.read().astype(np.float64)
                st_obs = ds.read_masks(1) > 0
            both = st_obs & tr.observed
            out["views"][n] = {
                "occluded_truth_dsm": round(float(tr.occluded.mean()), 4),
                "observed_stereo_dsm": round(float(st_obs.mean()), 4),
                "corr_stereo_vs_truth_dsm_ortho": round(
                    float(np.corrcoef(st_vals.mean(0)[both], grey(tr.values)[both])[0, 1]), 4
                ),
                "view_zenith_deg": round(float(np.nanmedian(tr.geometry.view_zenith_deg)), 1),
            }
    for a, b in (
        ("A_sat1", "A_sat4"),
        ("A_sat1", "A_air1"),
        ("A_sat4", "A_air3"),
        ("A_air1", "A_air3"),
        ("B_sat1", "B_sat3"),
    ):
        ra, rb = truth_orthos[a], truth_orthos[b]
        both = ra.observed & rb.observed
        rows, cols = np.flatnonzero(both.any(1)), np.flatnonzero(both.any(0))
        sl = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        out["pairs"][f"{a}/{b}"] = {
            "corr": round(float(np.corrcoef(grey(ra.values)[both], grey(rb.values)[both])[0, 1]), 4),
            "shift_cells": round(shift_cells(grey(ra.values)[sl], grey(rb.values)[sl], both[sl]), 3),
        }
    # classic vs true ortho of A_sat4, judged by the opposite view A_sat1 on the cells A_sat4 cannot see
    d = read_dem(AOI / "truth" / "dsm_A.tif")
    p = AOI / "images" / "A_sat4.tif"
    img = read_image(p)
    classic = orthorectify(
        img.data, load_camera(p), d.grid, d.height_m, valid=img.valid, params=OrthoParams(occlusion=False)
    )
    s1, s4 = truth_orthos["A_sat1"], truth_orthos["A_sat4"]
    occ = (s4.status == OCCLUDED) & s1.observed
    seen = s4.observed & s1.observed
    out["classic_vs_true"] = {
        "cells_hidden_from_A_sat4": int(occ.sum()),
        "corr_with_A_sat1_on_hidden_cells_classic": round(
            float(np.corrcoef(grey(s1.values)[occ], grey(classic.values)[occ])[0, 1]), 3
        ),
        "corr_with_A_sat1_on_seen_cells": round(
            float(np.corrcoef(grey(s1.values)[seen], grey(s4.values)[seen])[0, 1]), 3
        ),
    }
    (REPO / "bench" / "results" / "ortho_sample_aoi.json").write_text(json.dumps(out, indent=2))
    print(json.dumps(out, indent=2))

    # figure: classic vs true ortho of A_sat4 (stereo DSM run for the true one), and A_air2 (frame) true ortho
    sl = (slice(130, 330), slice(220, 420))

    def show(ax, vals, obs, title):
        g = grey(vals)
        lo, hi = np.percentile(g[obs], [2, 98])
        rgb = (
            np.dstack([np.clip((g - lo) / (hi - lo), 0, 1)] * 3)
            if vals.shape[0] == 1
            else np.clip(vals.transpose(1, 2, 0).astype(float) / 255.0, 0, 1)
        )
        rgb = rgb.copy()
        rgb[~obs] = (0.85, 0.1, 0.1)
        ax.imshow(rgb[sl], interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()

    import rasterio

    with rasterio.open(run / "ortho" / "A" / "A_sat4.tif") as ds:
        t_vals, t_obs = ds.read(), ds.read_masks(1) > 0
    with rasterio.open(run / "ortho" / "A" / "A_air2.tif") as ds:
        a_vals, a_obs = ds.read(), ds.read_masks(1) > 0
    fig, axs = plt.subplots(1, 3, figsize=(12, 4.8))
    show(axs[0], classic.values, classic.observed, "A_sat4, classic ortho (truth DSM):\nroofs smeared over the streets")
    show(axs[1], t_vals, t_obs, "A_sat4, true ortho (geocd stereo DSM):\nhidden cells masked (red)")
    show(axs[2], a_vals, a_obs, "A_air2 (frame camera), true ortho\n(geocd stereo DSM)")
    fig.tight_layout()
    fig.savefig(REPO / "docs" / "ortho_sample_aoi.png", dpi=80)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
