"""Relative orientation of a manifest's images: tie points → adjustment → corrected cameras on disk.

:func:`orient_manifest` is what ``geocd run``, ``geocd stereo``, ``geocd probchange`` and
``geocd orient`` call first. It writes ``<out>/orientation/<image>.camera.json`` (a
:class:`~geocd.camera.corrected.CorrectedCamera` around the image's own camera) and
``<out>/orientation/orientation.json`` (residuals before/after, per-image corrections, the tie
points' statistics), and returns a copy of the manifest whose images point at the corrected
cameras — so every later step sees corrected cameras through the ordinary camera protocol.
When the tie points are too few or ill-distributed the correction is not applied: the
manifest comes back unchanged, an :class:`OrientationWarning` says why, and the report records it.
A report whose inputs (images, cameras, parameters) are unchanged is reused.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress, sub_progress
from ..stereo.params import StereoParams
from ..stereo.scene import default_aoi_grid, footprint_xy, ground_height_hint, image_window_for_grid, load_epoch_images
from .adjust import OrientationResult, adjust
from .params import OrientationParams
from .tiepoints import OrthoView, find_tie_points, ortho_at_height, relief_displacement

REPORT_NAME = "orientation.json"


class OrientationWarning(UserWarning):
    """The cross-image correction was not applied (too few or ill-distributed tie points)."""


def orientation_params(manifest, override: OrientationParams | None = None) -> OrientationParams:
    """The manifest's ``orientation`` settings (``override`` wins when given)."""
    if override is not None:
        return override
    raw = (getattr(manifest, "extras", None) or {}).get("orientation")
    if raw is None or raw == "auto":
        return OrientationParams()
    if isinstance(raw, bool):
        return OrientationParams(enabled=raw)
    if isinstance(raw, dict):
        return OrientationParams.from_dict(raw)
    raise ConfigError(f"manifest 'orientation' must be true/false or a mapping, got {type(raw).__name__}")


def wants_orientation(manifest, params: OrientationParams) -> bool:
    """On when asked, or ("auto") when images of two or more epochs are in the manifest."""
    if params.enabled in (True, False):
        return bool(params.enabled)
    return sum(1 for e in manifest.epochs if len(e.images) >= 1) >= 2


def _signature(images: list, params: OrientationParams, grid: AOIGrid) -> str:
    h = hashlib.sha256()
    for ep, im in images:
        st = os.stat(im.path)
        h.update(f"{ep}|{im.name}|{Path(im.path).resolve()}|{st.st_size}|{st.st_mtime_ns}|".encode())
        h.update(json.dumps(im.camera.to_dict(), sort_keys=True, default=str).encode())
    h.update(params.to_json().encode())
    h.update(json.dumps(grid.to_dict(), sort_keys=True, default=str).encode())
    return h.hexdigest()


def _ortho_grid(grid: AOIGrid, max_px: int) -> AOIGrid:
    f = max(grid.shape) / float(max_px)
    if f <= 1.0:
        return grid
    l, b, r, t = grid.bounds
    return AOIGrid.from_bounds(l, b, r, t, grid.posting_m * f, grid.crs)


def orient_images(
    images: list,
    grid: AOIGrid,
    h0_m: float,
    params: OrientationParams = OrientationParams(),
    progress: Progress | None = None,
) -> OrientationResult:
    """Tie points and adjustment for ``images``: a list of (epoch name, EpochImage)."""
    from rasterio.windows import Window

    from ..io.raster import read_image

    prog = ensure_progress(progress)
    g = _ortho_grid(grid, params.max_ortho_px)
    views = []
    for i, (ep, im) in enumerate(images):
        prog(0.3 * i / len(images), f"ortho of {im.name}")
        from ..io.raster import _open

        with _open(im.path) as ds:
            W, H = ds.width, ds.height
        box = image_window_for_grid(im.camera, g, h0_m - 1.0, h0_m + 1.0, 4, W, H)
        if box is None:
            ortho = np.full(g.shape, np.nan, dtype=np.float32)
        else:
            c0, r0, c1, r1 = box
            img = read_image(im.path, window=Window(c0, r0, c1 - c0, r1 - r0))
            data = img.data.astype(np.float32).mean(axis=0)
            data[~img.valid] = np.nan
            ortho = ortho_at_height(data, c0, r0, im.camera, g, h0_m)
        views.append(OrthoView(im.name, ep, im.camera, ortho, relief_displacement(im.camera, g, h0_m)))
    tp = find_tie_points(views, g, h0_m, params, progress=sub_progress(prog, 0.3, 0.8, "tie points: "))
    prog(0.8, "adjustment")
    l, b, r, t = grid.bounds
    res = adjust([v.camera for v in views], tp, params, aoi_area_m2=(r - l) * (t - b))
    prog(1.0, "orientation done")
    return res


def orient_manifest(
    manifest,
    *,
    out_dir: os.PathLike | str,
    params: OrientationParams | None = None,
    grid: AOIGrid | None = None,
    progress: Progress | None = None,
    stereo_params: Any = None,
) -> tuple[Any, dict | None]:
    """Correct the manifest's cameras when its settings ask for it.

    Returns
    -------
    (manifest, report) — the manifest with corrected cameras (or unchanged), and the report dict
    (None when orientation is off).
    """
    from ..geodesy import as_crs
    from ..io.atomic import write_text_atomic

    p = orientation_params(manifest, params)
    if not wants_orientation(manifest, p):
        return manifest, None
    prog = ensure_progress(progress)
    sp = stereo_params or StereoParams()
    by_epoch = {e.name: load_epoch_images(manifest, e) for e in manifest.epochs if e.images}
    images = [(ep, im) for ep, ims in by_epoch.items() for im in ims]
    if len(images) < 2:
        return manifest, None
    h0 = None
    if grid is None:
        crs0 = as_crs(manifest.aoi.crs) if manifest.aoi is not None and manifest.aoi.crs else None
        if crs0 is None:
            from ..geodesy import utm_crs_for

            c = images[0][1].camera.footprint(float(np.mean(images[0][1].camera.height_range() or (0.0, 0.0)))).centroid
            crs0 = utm_crs_for(c.x, c.y)
        h0 = ground_height_hint([im for _, im in images], crs0, None, sp)
        check_epoch_overlap(by_epoch, crs0, h0, manifest.aoi.bounds if manifest.aoi is not None else None)
        grid = default_aoi_grid(manifest, by_epoch, params=sp, dem_median=h0)
    out = Path(out_dir) / "orientation"
    sig = _signature(images, p, grid)
    report_path = out / REPORT_NAME
    report = None
    if report_path.is_file():
        try:
            old = json.loads(report_path.read_text(encoding="utf-8"))
            if old.get("signature") == sig:
                report = old
        except (OSError, ValueError):
            report = None
    if report is None:
        prog(0.0, "relative orientation")
        if h0 is None:
            h0 = ground_height_hint([im for _, im in images], as_crs(grid.crs), None, sp)
        res = orient_images(images, grid, h0, p, progress=sub_progress(prog, 0.0, 1.0))
        out.mkdir(parents=True, exist_ok=True)
        cams = res.corrected_cameras([im.camera for _, im in images])
        files = {}
        if res.applied:
            for (ep, im), cam in zip(images, cams):
                path = write_text_atomic(
                    out / f"{im.name}.camera.json", json.dumps(cam.to_dict(), indent=1, default=str)
                )
                files[im.name] = str(path)
        report = {
            "geocd_orientation": 1,
            "signature": sig,
            "applied": res.applied,
            "reason": res.reason,
            "params": p.to_dict(),
            "images": [im.name for _, im in images],
            "epochs": [ep for ep, _ in images],
            "corrections": res.corrections.round(4).tolist(),
            "camera_files": files,
            **res.report,
        }
        write_text_atomic(report_path, json.dumps(report, indent=2, default=str))
        _write_tie_points(out / "tie_points.gpkg", res, grid)
    if not report["applied"]:
        if report.get("status") == "not needed":
            return manifest, report
        warnings.warn(
            f"cross-image orientation not applied: {report['reason']}; the cameras are used as given",
            OrientationWarning,
            stacklevel=2,
        )
        return manifest, report
    m2 = corrected_manifest(manifest, report)
    _write_oriented_manifest(out / "scene.oriented.yaml", m2)
    return m2, report


def _write_oriented_manifest(path: Path, m) -> None:
    """The manifest with corrected cameras (absolute paths; orientation off), for any later geocd command."""
    import yaml

    from ..io.atomic import write_text_atomic
    from ..io.manifest import manifest_to_dict

    d = manifest_to_dict(m)

    def ab(p):
        return None if p is None else str(Path(p).resolve())

    for e_d, e in zip(d["epochs"], m.epochs):
        e_d["images"] = [
            {"path": ab(i.path), "name": i.name, **({"camera": ab(i.camera)} if i.camera else {})} for i in e.images
        ]
        if e.dem is not None:
            e_d["dem"] = {
                "path": ab(e.dem.path),
                **({"vertical_datum": e.dem.vertical_datum} if e.dem.vertical_datum else {}),
            }
    for k, spec in (("dem", m.dem), ("footprints", m.footprints)):
        if spec is not None:
            d[k] = {
                "path": ab(spec.path),
                **({"vertical_datum": spec.vertical_datum} if getattr(spec, "vertical_datum", None) else {}),
            }
    d.pop("output", None)
    d["orientation"] = False
    d["description"] = f"{m.name} with the cameras corrected by geocd's relative orientation (orientation.json)"
    write_text_atomic(path, yaml.safe_dump(d, sort_keys=False, allow_unicode=True))


def check_epoch_overlap(by_epoch: dict, crs, h_m: float, aoi_bounds=None) -> None:
    """Raise :class:`~geocd.errors.NoOverlapError` when two epochs' ground footprints (at ``h_m``) do not overlap.

    ``by_epoch``: {epoch name: [EpochImage, ...]}; each epoch's footprint is the union of its images'. With an
    AOI (``aoi_bounds`` in ``crs``), each epoch must also reach it.
    """
    from shapely.geometry import box
    from shapely.ops import unary_union

    from ..errors import NoOverlapError

    fps = {e: unary_union([footprint_xy(im.camera, h_m, crs) for im in ims]) for e, ims in by_epoch.items() if ims}
    names = list(fps)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            inter = fps[a].intersection(fps[b])
            if inter.is_empty or inter.area <= 0:
                ca, cb = fps[a].centroid, fps[b].centroid
                raise NoOverlapError(
                    f"epochs {a!r} and {b!r} do not overlap on the ground (at {h_m:.0f} m their footprints are "
                    f"{ca.distance(cb) / 1000:.1f} km apart, centres ({ca.x:.0f}, {ca.y:.0f}) and ({cb.x:.0f}, "
                    f"{cb.y:.0f}) in {getattr(crs, 'name', crs)}); list images of the same place in both epochs"
                )
    if aoi_bounds is not None:
        aoi = box(*aoi_bounds)
        for e, f in fps.items():
            if not f.intersects(aoi):
                raise NoOverlapError(
                    f"the images of epoch {e!r} do not reach the AOI {tuple(aoi_bounds)}; fix the "
                    "AOI or the images of that epoch"
                )


def corrected_manifest(manifest, report: dict):
    """A copy of the manifest whose images use the corrected camera files named in ``report``."""
    files = report.get("camera_files", {})
    epochs = []
    for e in manifest.epochs:
        imgs = tuple(
            dataclasses.replace(im, camera=Path(files[im.name])) if im.name in files else im for im in e.images
        )
        epochs.append(dataclasses.replace(e, images=imgs))
    return dataclasses.replace(manifest, epochs=tuple(epochs))


def _write_tie_points(path: Path, res: OrientationResult, grid: AOIGrid) -> None:
    """Tie points as a point layer (track position in the reference ortho, images seeing it, inlier flag)."""
    tp = res.tie_points
    if tp is None or tp.n_tracks == 0:
        return
    import geopandas as gpd
    from shapely.geometry import Point

    from ..io.vector import write_gpkg

    inl = res.inliers if res.inliers is not None else np.ones(tp.image.size, bool)
    n_obs = np.bincount(tp.track, minlength=tp.n_tracks)
    n_in = np.bincount(tp.track[inl], minlength=tp.n_tracks)
    epochs = [sorted({tp.epochs[k] for k in tp.image[tp.track == t]}) for t in range(tp.n_tracks)]
    gdf = gpd.GeoDataFrame(
        {
            "track": np.arange(tp.n_tracks),
            "observations": n_obs,
            "inlier_observations": n_in,
            "epochs": [",".join(e) for e in epochs],
            "inlier": n_in >= 2,
        },
        geometry=[Point(x, y) for x, y in tp.xy0],
        crs=grid.crs,
    )
    write_gpkg(path, {"tie_points": gdf})
