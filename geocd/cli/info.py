"""``geocd info PATH``: what geocd sees in an image, camera file, DEM, vector or scene."""

from __future__ import annotations

import json

import click


def _fmt_camera(c: dict | None, indent: str = "  ") -> list[str]:
    if not c:
        return [f"{indent}camera: none (no RPC tags, no RPC sidecar, no frame sidecar)"]
    lines = [f"{indent}camera: {c['kind']}" + (f" ({c['source']})" if c.get("source") else "")]
    if c.get("width"):
        lines.append(f"{indent}  image size: {c['width']} x {c['height']} px")
    if "height_range_m" in c:
        lo, hi = c["height_range_m"]
        lines.append(f"{indent}  RPC height range: {lo:.1f} .. {hi:.1f} m (ellipsoidal)")
    if "centre_lonlat" in c:
        lines.append(f"{indent}  ground centre (lon, lat): {c['centre_lonlat'][0]:.6f}, {c['centre_lonlat'][1]:.6f}")
        lines.append(
            f"{indent}  footprint: {c['footprint_area_km2']} km2  GSD (col,row): {c['gsd_m'][0]} / {c['gsd_m'][1]} m"
            f"  off-nadir ~{c['off_nadir_deg']} deg (ground at {c['ground_height_m']:g} m)"
        )
        lines.append(
            f"{indent}  footprint (lon/lat WKT): {c['footprint_lonlat_wkt'][:160]}"
            + ("..." if len(c["footprint_lonlat_wkt"]) > 160 else "")
        )
    if "footprint_error" in c:
        lines.append(f"{indent}  footprint: unavailable ({c['footprint_error']})")
    return lines


def format_info(d: dict) -> str:
    t = d["type"]
    out = []
    if t == "raster":
        out.append(
            f"{d['path']}: raster ({d['driver']}) {d['width']} x {d['height']} x {d['bands']} {d['dtype']}"
            f", {d['bit_depth']}-bit"
        )
        out.append(
            f"  CRS: {d.get('crs', 'none')}"
            + (f"  vertical datum: {d['vertical_datum']}" if d.get("vertical_datum") else "")
        )
        if "bounds" in d:
            out.append(f"  bounds: {d['bounds']}  resolution: {d['resolution']}")
        if "geotransform" in d:
            out.append(f"  geotransform (no CRS): {d['geotransform']}")
        if "min" in d:
            out.append(f"  values: {d['min']:g} .. {d['max']:g}, valid {100 * d['valid_fraction']:.1f}%")
        else:
            out.append("  values: all nodata")
        if d.get("camera") is None and d.get("georeferenced"):
            out.append("  camera: none (a georeferenced raster: DEM or orthoimage)")
        else:
            out += _fmt_camera(d.get("camera"))
    elif t == "camera":
        out.append(f"{d['path']}: camera file")
        out += _fmt_camera(d["camera"])
    elif t == "vector":
        out.append(f"{d['path']}: vector")
        for l in d["layers"]:
            out.append(
                f"  layer {l['layer']}: {l['features']} {l['geometry'] or 'table'} features, CRS {l['crs']}, "
                f"fields {l['fields']}"
            )
    elif t == "products":
        word = "whole" if d["valid"] else "NOT whole"
        out.append(f"{d['path']}: geocd output folder, products {word}")
        for r in d["runs"]:
            out.append(
                f"  run {r['id']}: {r['command']}, {r['status']}, {r['products']} product(s)"
                + (f", {len(r['changed_or_missing'])} changed or missing" if r["changed_or_missing"] else "")
            )
        out += [f"  problem: {x}" for x in d["problems"]]
    elif t == "manifest":
        out.append(
            f"{d['path']}: scene {d['name']!r}" + (f" (class {d['scene_class']})" if d.get("scene_class") else "")
        )
        if d.get("aoi"):
            out.append(f"  AOI: {d['aoi']}")
        if d.get("dem"):
            out.append(f"  DEM: {d['dem']}")
        if d.get("footprints"):
            out.append(f"  footprints: {d['footprints']}")
        out.append(f"  output: {d['output']}")
        for e in d["epochs"]:
            out.append(
                f"  epoch {e['name']} ({e['date'] or 'no date'}{', ' + e['sensor'] if e['sensor'] else ''}): "
                f"{len(e['images'])} images" + (f", DEM {e['dem']}" if e.get("dem") else "")
            )
            for im in e["images"]:
                out.append(f"    {im['name']}: {im['path']}")
                out += _fmt_camera(im["camera"], indent="      ")
    return "\n".join(out)


@click.command("info")
@click.argument("path", type=click.Path(path_type=str))
@click.pass_context
def info(ctx: click.Context, path: str) -> None:
    """Print what geocd sees in PATH: camera kind, footprint on the ground, CRS, dtype, RPC height range.

    PATH may be an image (GeoTIFF/NITF with RPC tags or a camera sidecar), a camera file (any vendor RPC format or a
    geocd camera JSON/YAML), a DEM, a vector file, a scene manifest (scene.yaml) or a folder.

    For a geocd output folder: whether it holds whole product sets (every run complete, every product as
    written); exit status 1 when it does not (a run stopped half-way, a product changed since).
    """
    from .common import require_inputs, session

    require_inputs(path)
    from ..info import describe

    sess = session(ctx)
    d = describe(path)
    click.echo(json.dumps(d, indent=2, default=str) if sess.as_json else format_info(d))
    sess.stdout_done = True
    if d["type"] == "products" and not d["valid"]:
        ctx.exit(1)  # an output folder whose products are not whole sets: scripts must not publish it
