"""Probabilistic change detection on a scene manifest: read images, detect, write products.

The only part of :mod:`geocd.probchange` that touches files (with
:mod:`geocd.probchange.products`). The AOI grid, epoch choice, image loading and
image windows come from :mod:`geocd.stereo.scene` and :mod:`geocd.pipeline`,
so every method works on the same grid.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import os
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..camera import Camera
from ..errors import ConfigError, NoOverlapError
from ..geodesy import AOIGrid
from ..progress import Progress, ensure_progress, sub_progress
from ..stereo.scene import box_from_points
from .engine import View, make_view
from .keyframe import DEMSampler, KeyFrameResult, detect_keyframe, global_height_range
from .objectspace import ProbChangeResult, detect_objectspace, object_height_bounds
from .params import ProbChangeParams

VARIANTS = ("objectspace", "keyframe")


def _select(images: list, names: Sequence[str] | None, epoch: str) -> list:
    if not names:
        return list(images)
    by = {im.name: im for im in images}
    missing = [n for n in names if n not in by]
    if missing:
        raise ConfigError(f"image(s) {missing} are not in epoch {epoch!r}; its images are {sorted(by)}")
    return [by[n] for n in names]


def read_view(image, box: tuple[int, int, int, int], params: ProbChangeParams) -> View:
    """Read an image window ``(col0, row0, col1, row1)`` and normalize it into a :class:`View`."""
    from rasterio.windows import Window

    from ..io.raster import read_image

    c0, r0, c1, r1 = box
    img = read_image(image.path, window=Window(c0, r0, c1 - c0, r1 - r0))
    return make_view(
        img.data,
        image.camera,
        valid=img.valid,
        name=image.name,
        col0=c0,
        row0=r0,
        bands=params.bands,
        block_px=params.norm_block_px,
    )


def _image_size(path: Path) -> tuple[int, int]:
    from ..io.raster import _open

    with _open(path) as ds:
        return ds.width, ds.height


def key_window_boxes(
    key_cam: Camera, key_box: tuple[int, int, int, int], others: Sequence[Any], lo: float, hi: float, margin: int
) -> dict[str, tuple[int, int, int, int]]:
    """Image windows of the other views that the key window's rays reach between two heights."""
    c0, r0, c1, r1 = key_box
    cc, rr = np.meshgrid(np.linspace(c0, c1, 24), np.linspace(r0, r1, 24))
    out = {}
    for im in others:
        W, H = _image_size(im.path)
        cols, rows = [], []
        for h in (lo, 0.5 * (lo + hi), hi):
            lon, lat = key_cam.localize(cc, rr, np.full(cc.shape, h))
            c, r = im.camera.project(lon, lat, np.full(cc.shape, h))
            cols.append(c.ravel())
            rows.append(r.ravel())
        box = box_from_points(np.concatenate(cols), np.concatenate(rows), margin, W, H)
        if box is None:
            raise NoOverlapError(
                f"image {im.name!r} does not overlap the key frame's window {key_box} at heights "
                f"{lo:.0f}..{hi:.0f} m; drop it from its epoch or check its camera"
            )
        out[im.name] = box
    return out


def _swap_epoch_roles(res: ProbChangeResult) -> ProbChangeResult:
    """A result whose depth epoch was B, relabelled so height_a/height_b follow the manifest's A/B."""
    return dataclasses.replace(res, height_a_m=res.height_b_m, height_b_m=res.height_a_m)


def run_probchange(
    manifest,
    *,
    variant: str = "objectspace",
    key: str | None = None,
    epoch_a: str | None = None,
    epoch_b: str | None = None,
    images_a: Sequence[str] | None = None,
    images_b: Sequence[str] | None = None,
    out_dir: os.PathLike | str | None = None,
    params: ProbChangeParams = ProbChangeParams(),
    grid: AOIGrid | None = None,
    posting_m: float | None = None,
    write: bool = True,
    prefix: str | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Probabilistic change detection between two epochs of a manifest.

    Parameters
    ----------
    manifest : Manifest or path
    variant : "objectspace" (vertical rays on the AOI grid) or "keyframe" (rays of a key frame's pixels)
    key : key-frame image name (default: the first image of epoch A); its epoch is the depth epoch
    epoch_a, epoch_b : epochs to compare (default: first and last)
    images_a, images_b : names of the images to use in each epoch (default: all); for the object-space
        variant the first one is the reference of "star" pairs
    out_dir : output folder (default: the manifest's output)
    grid : AOI grid (default: :func:`geocd.stereo.scene.default_aoi_grid`)
    write : write the products

    Returns
    -------
    dict with ``result`` (ProbChangeResult on the grid), ``key_result`` (KeyFrameResult or None),
    ``grid``, ``outputs`` ({name: path}), ``summary`` (dict, also written as ``<prefix>_summary.json``).
    """
    from ..io.atomic import protect_inputs, write_text_atomic
    from ..io.manifest import Manifest, load_manifest
    from ..io.raster import read_dem
    from ..io.manifest import pick_epochs
    from ..stereo.scene import default_aoi_grid, image_window_for_grid, load_epoch_images
    from .products import write_keyframe_products, write_probchange_products

    if variant not in VARIANTS:
        raise ConfigError(f"variant must be one of {VARIANTS}, got {variant!r}")
    t_start = time.perf_counter()
    prog = ensure_progress(progress)
    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    from ..orientation import orient_manifest

    m, _ = orient_manifest(
        m, out_dir=Path(out_dir) if out_dir is not None else Path(m.output or m.root / "out"), grid=grid
    )
    ea, eb = pick_epochs(m, epoch_a, epoch_b)
    ims = {
        ea.name: _select(load_epoch_images(m, ea), images_a, ea.name),
        eb.name: _select(load_epoch_images(m, eb), images_b, eb.name),
    }
    protect_inputs(*[im.path for v in ims.values() for im in v])
    dem_obj = None
    dem_median = None
    if m.dem is not None:
        dem_obj = read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum).to_ellipsoidal()
        dem_median = float(np.nanmedian(dem_obj.height_m))
    if grid is None:
        grid = default_aoi_grid(m, ims, posting_m=posting_m, dem_median=dem_median)
    dem_grid = None
    if m.dem is not None:
        dem_grid = read_dem(m.dem.path, grid=grid, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m
    all_cams = [im.camera for v in ims.values() for im in v]
    margin = params.radius + 8
    prog(0.02, "reading images")
    swapped = False
    key_res: KeyFrameResult | None = None
    if variant == "objectspace":
        lo, hi, _ = object_height_bounds(grid, all_cams, dem_grid, params)
        lo_v, hi_v = float(np.min(lo)), float(np.max(hi))
        views = {}
        for e, lst in ims.items():
            views[e] = []
            for im in lst:
                W, H = _image_size(im.path)
                box = image_window_for_grid(im.camera, grid, lo_v, hi_v, margin, W, H)
                if box is None:
                    raise NoOverlapError(
                        f"image {im.name!r} of epoch {e!r} does not see the AOI {grid.bounds} at "
                        f"heights {lo_v:.0f}..{hi_v:.0f} m; drop it "
                        f"(--image-{'a' if e == ea.name else 'b'}) "
                        "or check its camera"
                    )
                views[e].append(read_view(im, box, params))
        res = detect_objectspace(
            views[ea.name],
            views[eb.name],
            grid,
            dem=dem_grid,
            params=params,
            progress=sub_progress(prog, 0.05, 0.9, "probchange: "),
        )
    else:
        key_name = key or ims[ea.name][0].name
        depth, other = (ea, eb) if key_name in {im.name for im in ims[ea.name]} else (eb, ea)
        if key_name not in {im.name for im in ims[depth.name]}:
            raise ConfigError(
                f"key frame {key_name!r} is not among the selected images of epochs {ea.name!r} and "
                f"{eb.name!r}: {[im.name for v in ims.values() for im in v]}"
            )
        swapped = depth.name != ea.name
        key_im = next(im for im in ims[depth.name] if im.name == key_name)
        others_a = [im for im in ims[depth.name] if im.name != key_name]
        dem_s = DEMSampler.wrap(dem_obj)
        lo_g, hi_g = global_height_range(all_cams, dem_s, params)
        W, H = _image_size(key_im.path)
        key_box = image_window_for_grid(key_im.camera, grid, lo_g, hi_g, 0, W, H)
        if key_box is None:
            raise NoOverlapError(f"key frame {key_name!r} does not see the AOI {grid.bounds}; pick another key frame")
        boxes = key_window_boxes(key_im.camera, key_box, others_a + list(ims[other.name]), lo_g, hi_g, margin)
        key_view = read_view(key_im, key_box, params)
        va = [read_view(im, boxes[im.name], params) for im in others_a]
        vb = [read_view(im, boxes[im.name], params) for im in ims[other.name]]
        key_res = detect_keyframe(
            key_view, va, vb, dem=dem_s, params=params, progress=sub_progress(prog, 0.05, 0.85, "probchange: ")
        )
        res = key_res.to_grid(grid)
        if swapped:
            key_res = _swap_epoch_roles(key_res)
            res = _swap_epoch_roles(res)
    prog(0.9, "writing products")
    outputs: dict[str, Path] = {}
    pairs = res.pairs
    summary = {
        "geocd_probchange": 1,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "manifest": str(m.path or m.root),
        "variant": variant,
        "epoch_a": ea.name,
        "epoch_b": eb.name,
        "depth_epoch": (eb.name if swapped else ea.name),
        "key_frame": key_res.key_name if key_res else None,
        "images": {e: [im.name for im in v] for e, v in ims.items()},
        "pairs": pairs,
        "noise_model": res.noise.to_dict(),
        "grid": grid.to_dict(),
        "params": params.to_dict(),
        "observed_fraction": round(float(res.observed.mean()), 4),
        "changed_fraction": round(float(res.changed().mean()), 5),
        "seconds": round(time.perf_counter() - t_start, 2),
    }
    if key_res is not None:
        summary["key_window"] = {
            "col0": key_res.col0,
            "row0": key_res.row0,
            "shape": list(key_res.probability.shape),
            "lattice_px": key_res.lattice_px,
        }
    if write:
        out = Path(out_dir) if out_dir is not None else m.output_dir()
        out.mkdir(parents=True, exist_ok=True)
        prefix = prefix or "probchange"
        prov = {"manifest": str(m.path or m.root), "variant": variant}
        outputs.update(
            write_probchange_products(out, res, epoch_a=ea.name, epoch_b=eb.name, prefix=prefix, provenance=prov)
        )
        if key_res is not None:
            outputs.update(
                write_keyframe_products(out, key_res, epoch_a=ea.name, epoch_b=eb.name, prefix=prefix, provenance=prov)
            )
        summary["outputs"] = {k: str(v) for k, v in outputs.items()}
        outputs["summary"] = write_text_atomic(
            out / f"{prefix}_summary.json", json.dumps(summary, indent=2, default=str)
        )
    prog(1.0, "done")
    return {"result": res, "key_result": key_res, "grid": grid, "outputs": outputs, "summary": summary}
