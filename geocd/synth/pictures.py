"""PNG quick-looks of a synthetic scene folder (for the README and docs)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def _stretch(a: np.ndarray, lo: float = 0.5, hi: float = 99.5) -> np.ndarray:
    v0, v1 = np.percentile(a, [lo, hi])
    return np.clip((a.astype(np.float64) - v0) / max(v1 - v0, 1e-9), 0, 1)


def _hillshade(z: np.ndarray, posting: float, az: float = 315.0, alt: float = 45.0) -> np.ndarray:
    gy, gx = np.gradient(z, posting)
    slope = np.arctan(np.hypot(gx, gy))
    aspect = np.arctan2(-gx, gy)
    a, e = np.radians(az), np.radians(alt)
    return np.clip(np.sin(e) * np.cos(slope) + np.cos(e) * np.sin(slope) * np.cos(a - aspect), 0, 1)


def write_pictures(scene_dir: os.PathLike | str, out_dir: os.PathLike | str, prefix: str = "sample_aoi_") -> dict:
    """Write ``<prefix>epoch_A.png``, ``epoch_B.png``, ``dsm.png`` and ``change.png``; returns name → path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    from ..io.manifest import load_manifest
    from ..io.raster import read_band
    from ..io.vector import read_footprints

    m = load_manifest(scene_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for ep in m.epochs:
        sats = [i for i in ep.images if "_sat" in i.name]
        airs = [i for i in ep.images if "_air" in i.name]
        panels = []
        if sats:
            panels.append(sats[len(sats) // 2])
        if airs:
            panels.append(airs[len(airs) // 2])
        fig, axs = plt.subplots(1, len(panels), figsize=(6.5 * len(panels), 6.8), squeeze=False)
        for ax, im in zip(axs[0], panels):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", NotGeoreferencedWarning)  # frames: no geotransform, by design
                with rasterio.open(im.path) as ds:
                    a = ds.read()
                    tags = ds.tags()
            if a.shape[0] == 1:
                ax.imshow(_stretch(a[0]), cmap="gray", interpolation="nearest")
                kind = "satellite pan, 11-bit, RPC"
            else:
                ax.imshow(np.moveaxis(a, 0, 2), interpolation="nearest")
                kind = "aerial RGB frame"
            ax.set_title(
                f"{im.name} ({kind})\nsun az {float(tags.get('SUN_AZIMUTH', 'nan')):.0f}°, "
                f"el {float(tags.get('SUN_ELEVATION', 'nan')):.0f}°",
                fontsize=10,
            )
            ax.set_axis_off()
        fig.suptitle(f"{m.name}: epoch {ep.name} ({ep.date}), {len(ep.images)} images", fontsize=12)
        fig.tight_layout()
        p = out / f"{prefix}epoch_{ep.name}.png"
        fig.savefig(p, dpi=80)
        plt.close(fig)
        written[f"epoch_{ep.name}"] = p
    # truth DSMs
    za, grid = read_band(m.truth_path("dsm_A"))
    zb, _ = read_band(m.truth_path("dsm_B"))
    lo, hi = np.nanpercentile(np.concatenate([za.ravel(), zb.ravel()]), [0.5, 99.8])
    ext = (grid.bounds[0], grid.bounds[2], grid.bounds[1], grid.bounds[3])
    fig, axs = plt.subplots(1, 2, figsize=(13, 6.2))
    for ax, z, name in zip(axs, (za, zb), ("A", "B")):
        hs = _hillshade(z, grid.posting_m)
        col = plt.get_cmap("terrain")(np.clip((z - lo) / (hi - lo), 0, 1))[..., :3]
        ax.imshow(col * (0.55 + 0.45 * hs[..., None]), extent=ext, interpolation="nearest")
        ax.set_title(f"truth DSM epoch {name} (ellipsoidal {lo:.0f}–{hi:.0f} m)", fontsize=10)
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    p = out / f"{prefix}dsm.png"
    fig.savefig(p, dpi=80)
    plt.close(fig)
    written["dsm"] = p
    # change mask by class, footprints by status
    cls, _ = read_band(m.truth_path("change_class"))
    n3d, _ = read_band(m.truth_path("non3d_mask"))
    img = np.full(cls.shape + (3,), 1.0)
    img[n3d == 2] = (0.88, 0.95, 0.85)
    img[n3d == 1] = (0.75, 0.75, 1.0)
    colours = {1: (0.85, 0.1, 0.1), 2: (0.1, 0.3, 0.9), 3: (0.1, 0.6, 0.1)}
    for k, c in colours.items():
        img[cls == k] = c
    fig, ax = plt.subplots(figsize=(10.5, 7.6))
    ax.imshow(img, extent=ext, interpolation="nearest")
    fp = read_footprints(m.truth_path("footprints_all"))
    style = {
        "new": "#d62728",
        "demolished": "#9467bd",
        "raised": "#ff7f0e",
        "lowered": "#17becf",
        "unchanged": "#444444",
    }
    for st, g in fp.groupby("status"):
        g.boundary.plot(
            ax=ax, color=style.get(st, "k"), linewidth=1.6 if st != "unchanged" else 0.6, label=f"{st} ({len(g)})"
        )
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(labelsize=7)
    from matplotlib.patches import Patch

    handles = ax.get_legend_handles_labels()[0] + [
        Patch(color=colours[1], label="3-D change: building"),
        Patch(color=colours[2], label="3-D change: car"),
        Patch(color=colours[3], label="3-D change: tree"),
        Patch(color=(0.75, 0.75, 1.0), label="repainted roof (not 3-D)"),
        Patch(color=(0.88, 0.95, 0.85), label="vegetation season (not 3-D)"),
    ]
    ax.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    thr = m.truth.get("change_threshold_m", 1.0)
    ax.set_title(f"truth change mask |ΔDSM| > {thr} m, footprints by status", fontsize=10)
    fig.tight_layout()
    p = out / f"{prefix}change.png"
    fig.savefig(p, dpi=80, bbox_inches="tight")
    plt.close(fig)
    written["change"] = p
    return written
