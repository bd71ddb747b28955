"""What geocd sees in a file or a scene (the engine behind ``geocd info``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from .errors import GeoCDError, InputFileNotFoundError, NoCameraError, UnsupportedFormatError
from .io.outputs import MANIFEST_NAME, check_product_set

VECTOR_SUFFIXES = (".gpkg", ".geojson", ".json", ".shp", ".fgb", ".kml", ".gml")


def camera_summary(cam, ground_h_m: float | None = None) -> dict[str, Any]:
    """Kind, height range, footprint and GSD of a camera.

    The ground is taken at ``ground_h_m`` (ellipsoidal; e.g. a DEM's median), else
    at the middle of the camera's height range, else at 0 m.
    """
    from .geodesy import LocalFrame

    d: dict[str, Any] = {"kind": cam.kind, "width": cam.width, "height": cam.height}
    hr = cam.height_range()
    if hr is not None:
        d["height_range_m"] = [float(hr[0]), float(hr[1])]
    h0 = ground_h_m if ground_h_m is not None else (0.5 * (hr[0] + hr[1]) if hr is not None else 0.0)
    d["ground_height_m"] = round(float(h0), 2)
    if getattr(cam, "source", ""):
        d["source"] = cam.source
    try:
        fp = cam.footprint(h0, reference=True)  # numpy path; the methods' localizer where it misses
        d["footprint_lonlat_wkt"] = fp.wkt
        c = fp.centroid
        d["centre_lonlat"] = [round(c.x, 7), round(c.y, 7)]
        # GSD: ground distance between neighbouring pixels at the image centre
        cc = cam.image_corners().mean(axis=0)
        lon, lat = cam.localize_summary([cc[0], cc[0] + 1, cc[0]], [cc[1], cc[1], cc[1] + 1], [h0] * 3)
        f = LocalFrame(float(lon[0]), float(lat[0]), h0)
        e, n, _ = f.to_enu(lon, lat, [h0] * 3)
        d["gsd_m"] = [
            round(float(np.hypot(e[1] - e[0], n[1] - n[0])), 4),
            round(float(np.hypot(e[2] - e[0], n[2] - n[0])), 4),
        ]
        # incidence: image motion per metre of height at the centre (px/m) ~ tan(off-nadir)/gsd
        dc, dr = cam.dproj_dh_reference(lon[:1], lat[:1], [h0])
        d["dproj_dh_px_per_m"] = [round(float(dc[0]), 5), round(float(dr[0]), 5)]
        gsd = 0.5 * sum(d["gsd_m"])
        d["off_nadir_deg"] = round(float(np.degrees(np.arctan(np.hypot(dc[0], dr[0]) * gsd))), 2)
        d["footprint_area_km2"] = round(_area_km2(fp), 4)
    except GeoCDError as exc:
        d["footprint_error"] = str(exc)
    return d


def _area_km2(poly_lonlat) -> float:
    from pyproj import Geod

    return abs(Geod(ellps="WGS84").geometry_area_perimeter(poly_lonlat)[0]) / 1e6


def raster_summary(path: Path) -> dict[str, Any]:

    from .geodesy import vertical_datum_of
    from .io.raster import effective_bit_depth

    from .io.raster import _open

    ds = _open(path)
    with ds:
        d: dict[str, Any] = {
            "type": "raster",
            "path": str(path),
            "driver": ds.driver,
            "width": ds.width,
            "height": ds.height,
            "bands": ds.count,
            "dtype": ds.dtypes[0],
            "nodata": ds.nodata,
        }
        if ds.crs:
            from .geodesy import as_crs

            c = as_crs(ds.crs)
            d["crs"] = f"EPSG:{c.to_epsg()}" if c.to_epsg() else c.name
            d["vertical_datum"] = vertical_datum_of(ds.crs)
            d["bounds"] = list(ds.bounds)
            d["resolution"] = list(ds.res)
        elif not ds.transform.is_identity:
            d["geotransform"] = list(ds.transform)[:6]
        tags = ds.tags(1) | ds.tags(1, "IMAGE_STRUCTURE")
        # sample for statistics without reading huge rasters whole
        step = max(1, int(np.ceil(max(ds.width, ds.height) / 1024)))
        arr = ds.read(1, out_shape=(max(1, ds.height // step), max(1, ds.width // step)), masked=True)
        d["bit_depth"] = effective_bit_depth(arr.compressed() if arr.count() else arr.data, tags)
        if arr.count():
            d["min"], d["max"] = float(arr.min()), float(arr.max())
            d["valid_fraction"] = round(float(arr.count() / arr.size), 4)
        else:
            d["valid_fraction"] = 0.0
    try:
        from .io.cameras import load_camera

        d["camera"] = camera_summary(load_camera(path))
    except NoCameraError:
        d["camera"] = None
        d["georeferenced"] = "crs" in d
    return d


def vector_summary(path: Path) -> dict[str, Any]:
    import pyogrio

    try:
        layers = pyogrio.list_layers(path)
    except Exception as exc:
        raise UnsupportedFormatError(f"cannot read {path} as a vector source ({exc})") from exc
    out = []
    for name, geom in layers:
        info = pyogrio.read_info(path, layer=name)
        out.append(
            {
                "layer": name,
                "geometry": geom,
                "features": int(info["features"]),
                "crs": info.get("crs"),
                "fields": list(info["fields"]),
            }
        )
    return {"type": "vector", "path": str(path), "layers": out}


def manifest_summary(path: Path) -> dict[str, Any]:
    from .io.cameras import load_camera
    from .io.manifest import load_manifest

    m = load_manifest(path)
    d: dict[str, Any] = {
        "type": "manifest",
        "path": str(m.path or path),
        "name": m.name,
        "scene_class": m.scene_class,
        "output": str(m.output_dir()),
        "epochs": [],
    }
    if m.aoi is not None:
        d["aoi"] = {"crs": m.aoi.crs, "bounds": m.aoi.bounds, "posting_m": m.aoi.posting_m}
    if m.dem is not None:
        d["dem"] = str(m.dem.path)
    if m.footprints is not None:
        d["footprints"] = str(m.footprints.path)
    ground = None
    if m.dem is not None:
        from .io.raster import read_dem

        try:
            ground = float(
                np.nanmedian(read_dem(m.dem.path, vertical_datum=m.dem.vertical_datum).to_ellipsoidal().height_m)
            )
        except GeoCDError:
            ground = None
    for e in m.epochs:
        ed: dict[str, Any] = {
            "name": e.name,
            "date": e.date.isoformat() if e.date else None,
            "sensor": e.sensor,
            "images": [],
        }
        for im in e.images:
            cam = load_camera(im.path, im.camera)
            s = camera_summary(cam, ground)
            ed["images"].append({"name": im.name, "path": str(im.path), "camera": s})
        if e.dem is not None:
            ed["dem"] = str(e.dem.path)
        d["epochs"].append(ed)
    return d


def describe(path: os.PathLike | str) -> dict[str, Any]:
    """Everything geocd can tell about ``path`` (image, camera file, DEM, vector, manifest, folder)."""
    p = Path(path)
    if not p.exists():
        raise InputFileNotFoundError(f"{p} does not exist; check the path")
    suffix = p.suffix.lower()
    if p.is_dir() and (p / MANIFEST_NAME).is_file():  # an output folder: are its product sets whole?
        return {"type": "products", "path": str(p), **check_product_set(p)}
    if p.is_dir() or suffix in (".yaml", ".yml"):
        return manifest_summary(p)
    if suffix in VECTOR_SUFFIXES:
        if suffix == ".json":
            import json

            try:
                d = json.loads(p.read_text(encoding="utf-8"))
            except Exception:
                d = None
            if isinstance(d, dict) and ("kind" in d or "rpc" in d) or (isinstance(d, dict) and "epochs" in d):
                if "epochs" in d:
                    return manifest_summary(p)
                from .io.cameras import read_camera_file

                return {"type": "camera", "path": str(p), "camera": camera_summary(read_camera_file(p))}
        return vector_summary(p)
    try:
        return raster_summary(p)
    except UnsupportedFormatError:
        from .io.cameras import read_camera_file

        return {"type": "camera", "path": str(p), "camera": camera_summary(read_camera_file(p))}
