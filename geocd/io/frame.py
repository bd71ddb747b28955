"""Frame-camera files: geocd's sidecar, and orthority/ngi orientation files.

geocd frame sidecar
-------------------
One camera per image, in ``<image stem>.camera.json`` (or ``.camera.yaml`` /
``.camera.yml``) next to the image, e.g. ``IMG_0182.tif`` →
``IMG_0182.camera.json``. :func:`find_frame_sidecar` looks there;
:func:`write_frame_sidecar` writes it (atomically). The content is
:meth:`FrameCamera.to_dict <geocd.camera.frame.FrameCamera.to_dict>`::

    kind: frame                      # required
    crs: EPSG:32735                  # projected CRS (metres) of x, y; EPSG code or WKT
    vertical_datum: egm2008          # z's datum: ellipsoid | egm96 | egm2008
                                     # (may be omitted when crs is compound)
    width: 640                       # image size, pixels
    height: 1152
    focal_px: 833.333                # focal length in pixels, or [fx, fy]
    #   or: focal_mm: 120.0 with pixel_size_mm: 0.144 (or [sx, sy])
    principal_point_px: [320.0, 576.0]   # [col, row], pixels from the upper-left
                                     # image CORNER; default the image centre
    #   or: principal_point_mm: [dx, dy]  offset from the image centre in mm,
    #       along columns (right) and rows (down); needs pixel_size_mm
    #   principal_point: [col, row]  is accepted as an alias of principal_point_px
    distortion: {k1: 0.0, k2: 0.0, k3: 0.0, p1: 0.0, p2: 0.0}
                                     # optional; OpenCV Brown–Conrady on normalised
                                     # image coordinates; missing keys are 0
    position: [x, y, z]              # projection centre, metres (crs, vertical_datum)
    opk_deg: [omega, phi, kappa]     # degrees, orthority/PATB convention
    #   or: opk_rad: [...]           # radians
    allow_geoid_substitute: false    # optional: EGM96 grid for EGM2008 when missing
    source: "..."                    # optional provenance

See :mod:`geocd.camera.frame` for the conventions (rotation, pixel origin, the
Cartesian treatment of the projected CRS + height frame).

orthority / ngi files
---------------------
:func:`read_orthority_cameras` reads an orthority interior-parameter YAML
(``{camera id: {type, im_size, focal_len, sensor_size, cx, cy, k1, ...}}``)
with an exterior-parameter file: orthority CSV (``filename, x|easting,
y|northing, z|altitude, omega, phi, kappa[, camera]`` in degrees, comma/space/tab
separated, header optional, CRS from a ``.prj`` beside it or ``crs=``), ngi's
``camera_pos_ori.txt`` (the same columns without header; give ``crs=``) or
orthority GeoJSON (``world_crs``, properties ``filename, camera, xyz, opk`` in
radians). Neither format records the vertical datum of ``z``: give
``vertical_datum=`` (that of the DEM used for the triangulation).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

from ..camera.frame import FrameCamera
from ..errors import FrameCameraError, GeoCDError, InputFileNotFoundError, UnsupportedFormatError
from .safe_yaml import YAMLLimitError, load_json, load_yaml

#: sidecar suffixes, in search order
SIDECAR_SUFFIXES = (".camera.json", ".camera.yaml", ".camera.yml")


# ------------------------------------------------------------------------------------------
# geocd sidecar
# ------------------------------------------------------------------------------------------
def sidecar_path_for(image_path: os.PathLike | str, fmt: str = "json") -> Path:
    """Where the frame sidecar of ``image_path`` goes: ``<stem>.camera.<fmt>`` beside it."""
    fmt = fmt.lower().lstrip(".")
    if fmt not in ("json", "yaml", "yml"):
        raise FrameCameraError(f"frame sidecar format {fmt!r} is not supported; use 'json' or 'yaml'")
    p = Path(image_path)
    return p.with_name(f"{p.stem}.camera.{fmt}")


def find_frame_sidecar(image_path: os.PathLike | str) -> Path | None:
    """The frame sidecar of an image (``<stem>.camera.json|yaml|yml`` or ``<name>.camera.*``), or None."""
    p = Path(image_path)
    for base in (p.stem, p.name):
        for suf in SIDECAR_SUFFIXES:
            c = p.with_name(base + suf)
            if c.is_file():
                return c
    return None


def _is_sidecar_name(p: Path) -> bool:
    return p.suffix.lower() in (".json", ".yaml", ".yml")


def _load_mapping(path: Path) -> Any:
    text = path.read_text(encoding="utf-8", errors="replace")
    if path.suffix.lower() == ".json":
        try:
            return load_json(text)
        except YAMLLimitError as exc:
            raise FrameCameraError(f"{path}: {exc}") from None
        except json.JSONDecodeError as exc:
            raise FrameCameraError(
                f"{path} is not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg}); fix the syntax"
            ) from exc
    import yaml

    try:
        return load_yaml(text)
    except YAMLLimitError as exc:
        raise FrameCameraError(f"{path}: {exc}") from None
    except yaml.YAMLError as exc:
        first = " ".join(str(exc).split())[:200]
        raise FrameCameraError(f"{path} is not valid YAML ({first}); fix the syntax") from None


def read_frame_sidecar(path: os.PathLike | str) -> FrameCamera:
    """Read a geocd frame sidecar (JSON or YAML; schema in the module docstring)."""
    p = Path(path)
    if not p.is_file():
        raise InputFileNotFoundError(f"frame camera sidecar {p} does not exist; check the path")
    if not _is_sidecar_name(p):
        raise UnsupportedFormatError(f"{p} is not a frame sidecar; geocd reads <image stem>.camera.json or .yaml")
    d = _load_mapping(p)
    if not isinstance(d, Mapping):
        raise FrameCameraError(f"{p} does not hold a mapping of camera fields; see geocd.io.frame for the schema")
    try:
        cam = FrameCamera.from_dict(d)
    except FrameCameraError as exc:
        raise FrameCameraError(f"{p}: {exc}") from exc
    except GeoCDError:
        raise
    except (TypeError, ValueError, ArithmeticError) as exc:  # a value no field check foresaw
        raise FrameCameraError(
            f"{p}: invalid frame camera ({type(exc).__name__}: {str(exc)[:160]}); see geocd.io.frame for the schema"
        ) from None
    if not cam.source:
        cam = cam.replace(source=str(p))
    return cam


def write_frame_sidecar(
    path: os.PathLike | str, camera: FrameCamera, *, fmt: str | None = None, overwrite: bool = True
) -> Path:
    """Write a frame camera as a geocd sidecar (atomically).

    Parameters
    ----------
    path : the sidecar path (``*.json``, ``*.yaml``, ``*.yml``) or the image path,
        in which case the sidecar is ``<stem>.camera.json`` (or ``fmt``) beside it.
    camera : FrameCamera
    fmt : "json" or "yaml", for an image path (default json).
    overwrite : bool
        Replace an existing sidecar (default True).

    Returns
    -------
    Path of the written sidecar.
    """
    from .atomic import check_output_path, write_text_atomic

    if not isinstance(camera, FrameCamera):
        raise FrameCameraError(f"write_frame_sidecar needs a FrameCamera, got {type(camera).__name__}")
    p = Path(path)
    if not _is_sidecar_name(p) or fmt is not None:
        p = sidecar_path_for(p, fmt or "json")
    check_output_path(p, overwrite=overwrite)
    d = camera.to_dict()
    if p.suffix.lower() == ".json":
        text = json.dumps(d, indent=2) + "\n"
    else:
        import yaml

        text = yaml.safe_dump(d, sort_keys=False, default_flow_style=None)
    return write_text_atomic(p, text)


# ------------------------------------------------------------------------------------------
# orthority / ngi
# ------------------------------------------------------------------------------------------
_X_NAMES = ("x", "easting")
_Y_NAMES = ("y", "northing")
_Z_NAMES = ("z", "altitude", "height")
_DEFAULT_COLUMNS = ("filename", "x", "y", "z", "omega", "phi", "kappa", "camera")


def orthority_interior_to_kw(params: Mapping[str, Any], *, where: str = "interior parameters") -> dict:
    """One orthority interior-parameter entry → :class:`FrameCamera` keyword arguments.

    orthority: ``fx = focal_len * width / sensor_width`` (``focal_len`` is
    normalised by the image width when ``sensor_size`` is absent); principal
    point ``(w - 1) / 2 + max(w, h) * cx`` with pixel centres at integers, i.e.
    ``w / 2 + max(w, h) * cx`` in geocd's corner convention.
    """
    p = dict(params)
    ctype = str(p.pop("type", "pinhole")).lower()
    if ctype not in ("pinhole", "brown", "opencv"):
        raise FrameCameraError(
            f"{where}: camera type {ctype!r} is not supported (geocd frame cameras are pinhole with "
            "Brown–Conrady distortion: types pinhole, brown, opencv); undistort the images first"
        )
    try:
        im_size = p.pop("im_size")
        focal = p.pop("focal_len")
    except KeyError as exc:
        raise FrameCameraError(
            f"{where}: missing {exc}; orthority interior parameters need im_size and focal_len"
        ) from exc
    sensor = p.pop("sensor_size", None)
    cx = float(p.pop("cx", 0.0) or 0.0)
    cy = float(p.pop("cy", 0.0) or 0.0)
    try:
        w, h = (int(v) for v in im_size)
    except (TypeError, ValueError) as exc:
        raise FrameCameraError(f"{where}: im_size={im_size!r} must be [width, height] in pixels") from exc
    try:
        f = [float(v) for v in (focal if isinstance(focal, (list, tuple)) else [focal, focal])]
        if sensor is None:
            fx, fy = f[0] * w, f[1] * w
        else:
            sw, sh = (float(v) for v in sensor)
            fx, fy = f[0] * w / sw, f[1] * h / sh
    except (TypeError, ValueError, ZeroDivisionError) as exc:
        raise FrameCameraError(f"{where}: focal_len={focal!r} / sensor_size={sensor!r} are not valid numbers") from exc
    dist = {}
    for k in ("k1", "k2", "k3", "p1", "p2"):
        if k in p:
            dist[k] = float(p.pop(k))
    extra = {k: v for k, v in p.items() if k in ("k4", "k5", "k6", "s1", "s2", "s3", "s4", "tx", "ty")}
    if any(float(v) != 0.0 for v in extra.values()):
        raise FrameCameraError(
            f"{where}: distortion coefficients {sorted(extra)} are not supported (geocd uses k1, k2, k3, p1, p2); "
            "undistort the images first"
        )
    m = max(w, h)
    return dict(
        width=w,
        height=h,
        focal_px=(fx, fy),
        principal_point_px=(w / 2.0 + m * cx, h / 2.0 + m * cy),
        distortion=dist or None,
    )


def read_orthority_int_param(path: os.PathLike | str) -> dict[str, dict]:
    """orthority interior-parameter YAML/JSON → ``{camera id: FrameCamera keyword arguments}``."""
    p = Path(path)
    if not p.is_file():
        raise InputFileNotFoundError(f"interior parameter file {p} does not exist; check the path")
    d = _load_mapping(p)
    if not isinstance(d, Mapping) or not d:
        raise FrameCameraError(f"{p} holds no cameras; orthority interior files map camera ids to parameters")
    if "im_size" in d:  # a single camera without an id
        d = {p.stem: d}
    out = {}
    for cam_id, params in d.items():
        if not isinstance(params, Mapping):
            raise FrameCameraError(f"{p}: camera {cam_id!r} is not a mapping of interior parameters")
        out[str(cam_id)] = orthority_interior_to_kw(params, where=f"{p} camera {cam_id!r}")
    return out


def _read_prj(path: Path) -> str | None:
    prj = path.with_suffix(".prj")
    if prj.is_file():
        return prj.read_text(encoding="utf-8", errors="replace").strip()
    return None


def _csv_dialect(lines: list[str]) -> tuple[str, str]:
    """Delimiter and quote character of an orthority CSV (as orthority accepts them).

    The delimiter is one of ``, ; : tab space`` and the quote ``"`` or ``'`` (camera names
    with spaces come quoted); both are what splits every line into the same number of
    fields — the most fields wins, so a comma inside a quoted name does not make a
    space-separated file comma-separated.
    """
    sample = lines[: min(len(lines), 20)]
    best = None
    for quote in ('"', "'"):
        n_quotes = sum(line.count(quote) for line in sample)
        for order, delim in enumerate((",", ";", "\t", ":", " ")):
            rows = csv.reader(io.StringIO("\n".join(sample)), delimiter=delim, skipinitialspace=True, quotechar=quote)
            counts = {len([c for c in r if c.strip() != ""]) for r in rows}
            if len(counts) != 1 or min(counts) < 7:
                continue
            key = (min(counts) in (7, 8), n_quotes, -order)
            if best is None or key > best[0]:
                best = (key, delim, quote)
    if best is None:  # let the row check below name the problem
        first = lines[0]
        return ("," if "," in first else ("\t" if "\t" in first else " ")), '"'
    return best[1], best[2]


def _read_ext_csv(p: Path) -> list[dict]:
    text = p.read_text(encoding="utf-8-sig", errors="replace")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise FrameCameraError(f"{p} holds no camera rows; it needs filename x y z omega phi kappa per line")
    delim, quote = _csv_dialect(lines)
    reader = csv.reader(io.StringIO("\n".join(lines)), delimiter=delim, skipinitialspace=True, quotechar=quote)
    rows = [[c.strip() for c in r if c.strip() != ""] for r in reader]
    header = [c.lower() for c in rows[0]]

    def is_number(s: str) -> bool:
        try:
            float(s)
            return True
        except ValueError:
            return False

    if "filename" in header or not any(is_number(c) for c in rows[0][1:]):
        cols, data = header, rows[1:]
    else:
        cols, data = list(_DEFAULT_COLUMNS), rows
    if {"latitude", "longitude"} & set(cols) or {"roll", "pitch", "yaw"} & set(cols):
        raise FrameCameraError(
            f"{p}: latitude/longitude or roll/pitch/yaw columns are not supported; give x, y, z in a projected "
            "CRS and omega, phi, kappa in degrees (convert with orthority's tools)"
        )

    def col(names: tuple[str, ...]) -> int:
        for n in names:
            if n in cols:
                return cols.index(n)
        raise FrameCameraError(f"{p}: no column named {' or '.join(names)}; columns are {cols}")

    ix = {
        "filename": col(("filename",)),
        "x": col(_X_NAMES),
        "y": col(_Y_NAMES),
        "z": col(_Z_NAMES),
        "omega": col(("omega",)),
        "phi": col(("phi",)),
        "kappa": col(("kappa",)),
    }
    icam = cols.index("camera") if "camera" in cols else None
    out = []
    for k, r in enumerate(data, start=2 if data is not rows else 1):
        try:
            vals = {n: float(r[i]) for n, i in ix.items() if n != "filename"}
            name = r[ix["filename"]]
        except (IndexError, ValueError) as exc:
            raise FrameCameraError(f"{p} row {k}: {r} does not give filename x y z omega phi kappa as numbers") from exc
        out.append(
            {
                "filename": name,
                "xyz": (vals["x"], vals["y"], vals["z"]),
                "opk_deg": (vals["omega"], vals["phi"], vals["kappa"]),
                "camera": r[icam] if icam is not None and icam < len(r) else None,
            }
        )
    return out


def _read_ext_geojson(p: Path) -> tuple[list[dict], str | None]:
    try:
        d = json.loads(p.read_text(encoding="utf-8", errors="replace"))
    except json.JSONDecodeError as exc:
        raise FrameCameraError(
            f"{p} is not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg}); fix the syntax"
        ) from exc
    feats = d.get("features") if isinstance(d, Mapping) else None
    if not feats:
        raise FrameCameraError(f"{p} has no features; orthority exterior GeoJSON holds one Point feature per image")
    out = []
    for k, f in enumerate(feats):
        props = f.get("properties") or {}
        try:
            name = props["filename"]
            xyz = tuple(float(v) for v in props["xyz"])
            opk = tuple(math.degrees(float(v)) for v in props["opk"])
        except (KeyError, TypeError, ValueError) as exc:
            raise FrameCameraError(
                f"{p} feature {k}: properties need filename, xyz [x, y, z] and opk [omega, phi, kappa] "
                f"(radians) ({exc})"
            ) from exc
        out.append({"filename": name, "xyz": xyz, "opk_deg": opk, "camera": props.get("camera")})
    return out, d.get("world_crs")


def read_orthority_ext_param(path: os.PathLike | str, crs: Any = None) -> tuple[list[dict], Any]:
    """Exterior orientation rows ``{filename, xyz, opk_deg, camera}`` and the CRS they are in."""
    p = Path(path)
    if not p.is_file():
        raise InputFileNotFoundError(f"exterior parameter file {p} does not exist; check the path")
    suf = p.suffix.lower()
    if suf in (".geojson", ".json"):
        rows, file_crs = _read_ext_geojson(p)
    elif suf in (".csv", ".txt"):
        rows, file_crs = _read_ext_csv(p), _read_prj(p)
    else:
        raise UnsupportedFormatError(
            f"{p}: exterior orientation format {suf!r} is not supported; use orthority CSV (.csv/.txt) or GeoJSON"
        )
    use = crs if crs is not None else file_crs
    if use is None:
        raise FrameCameraError(
            f"{p} does not say which CRS its x, y are in; pass crs= (e.g. the CRS of the images or DEM) or put "
            f"a {p.with_suffix('.prj').name} beside it"
        )
    return rows, use


def read_orthority_cameras(
    int_param_path: os.PathLike | str,
    ext_param_path: os.PathLike | str,
    *,
    crs: Any = None,
    vertical_datum: str | None = None,
    allow_geoid_substitute: bool = False,
) -> dict[str, FrameCamera]:
    """orthority/ngi interior + exterior files → ``{image name: FrameCamera}``.

    Parameters
    ----------
    int_param_path : orthority interior-parameter YAML
    ext_param_path : orthority CSV / ngi ``camera_pos_ori.txt`` / orthority GeoJSON
    crs : CRS of the exterior orientation; default from the file (.prj or world_crs)
    vertical_datum : datum of the camera z and of ground heights in that frame
        ("ellipsoid", "egm96", "egm2008"); required unless ``crs`` is compound.
    allow_geoid_substitute : use EGM96 where the EGM2008 grid is missing

    Returns
    -------
    dict keyed by the file's image names (orthority writes stems without extension).
    """
    cams = read_orthority_int_param(int_param_path)
    rows, use_crs = read_orthority_ext_param(ext_param_path, crs)
    out: dict[str, FrameCamera] = {}
    for r in rows:
        cid = r["camera"]
        if cid is None:
            if len(cams) != 1:
                raise FrameCameraError(
                    f"{ext_param_path}: image {r['filename']!r} names no camera and {int_param_path} holds "
                    f"{len(cams)} cameras {sorted(cams)}; add a 'camera' column"
                )
            cid = next(iter(cams))
        if cid not in cams:
            raise FrameCameraError(
                f"{ext_param_path}: image {r['filename']!r} uses camera {cid!r}, which {int_param_path} does not "
                f"define (it has {sorted(cams)})"
            )
        try:
            out[r["filename"]] = FrameCamera(
                position=r["xyz"],
                opk_deg=r["opk_deg"],
                crs=use_crs,
                vertical_datum=vertical_datum,
                allow_geoid_substitute=allow_geoid_substitute,
                source=f"orthority {Path(int_param_path).name} + {Path(ext_param_path).name}",
                **cams[cid],
            )
        except FrameCameraError as exc:
            raise FrameCameraError(f"{ext_param_path} image {r['filename']!r}: {exc}") from exc
    return out
