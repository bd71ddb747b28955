"""Fuzz targets shared by the hypothesis tests (short runs in CI) and bench/fuzz_inputs.py (long runs).

Each ``check_*`` function feeds one mutated input to a geocd reader and returns the outcome: ``"ok"`` or the
name of the :class:`~geocd.errors.GeoCDError` raised. Any other exception propagates: that is a failure.
"""

from __future__ import annotations

import copy
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from hypothesis import strategies as st

from geocd.errors import GeoCDError

# ------------------------------------------------------------------------------------------------------------
# byte mutations (truncate / insert / delete / flip), half of them in the first kilobyte (headers, TIFF tags)
# ------------------------------------------------------------------------------------------------------------
byte_mutations = st.tuples(
    st.sampled_from(["truncate", "insert", "delete", "flip"]),
    st.floats(0.0, 1.0),
    st.binary(min_size=1, max_size=12),
    st.integers(1, 40),
    st.integers(0, 2**32 - 1),
    st.booleans(),
)


def mutate_bytes(data: bytes, mutation) -> bytes:
    how, pos, payload, count, seed, head = mutation
    n = len(data)
    span = min(n, 1024) if head else n
    i = min(int(pos * span), n)
    rnd = np.random.default_rng(seed)
    if how == "truncate":
        return data[:i]
    if how == "insert":
        return data[:i] + payload + data[i:]
    if how == "delete":
        return data[:i] + data[i + count :]
    b = bytearray(data)
    for j in rnd.integers(0, max(span, 1), size=count):
        if n:
            b[int(j)] = int(rnd.integers(0, 256))
    return bytes(b)


def _outcome(fn, *a, **kw) -> str:
    try:
        fn(*a, **kw)
    except GeoCDError as exc:
        return type(exc).__name__
    return "ok"


# ------------------------------------------------------------------------------------------------------------
# manifests: structural mutations of a valid document, and byte mutations of its YAML text
# ------------------------------------------------------------------------------------------------------------
_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.sampled_from(
        [
            "",
            "fine",
            "a",
            "2024-13-45",
            "2023-06-01",
            "EPSG:32631",
            "EPSG:99999",
            "images/A_0.tif",
            "../../nope",
            "dem.tif",
            "egm96",
            "wgs1234",
            "1e3",
        ]
    ),
    st.lists(st.one_of(st.integers(-5, 5), st.floats(-1e6, 1e6), st.text(max_size=3)), max_size=5),
    st.dictionaries(st.sampled_from(["path", "name", "x", "images", "date", "layer"]), st.text(max_size=6), max_size=3),
)
tree_ops = st.lists(
    st.tuples(
        st.sampled_from(["replace", "rename", "delete", "add"]), st.integers(0, 10**6), _VALUES, st.integers(0, 10**6)
    ),
    min_size=1,
    max_size=4,
)


def _slots(node: Any, out: list) -> list:
    if isinstance(node, dict):
        for k in list(node):
            out.append((node, k))
            _slots(node[k], out)
    elif isinstance(node, list):
        for i in range(len(node)):
            out.append((node, i))
            _slots(node[i], out)
    return out


def _typo(key: str, r: int) -> str:
    if not key:
        return "x"
    i = r % len(key)
    k = r % 3
    if k == 0:
        return key[:i] + key[i + 1 :] or "x"  # drop a letter (camra)
    if k == 1:
        return key[:i] + key[i] + key[i:]  # double a letter
    return key + "z"  # imagez


def mutate_tree(doc: dict, ops) -> dict:
    d = copy.deepcopy(doc)
    for kind, where, value, r in ops:
        slots = _slots(d, [])
        if not slots:
            break
        parent, key = slots[where % len(slots)]
        if kind == "replace":
            parent[key] = value
        elif kind == "delete":
            del parent[key]
        elif kind == "rename" and isinstance(parent, dict):
            parent[_typo(str(key), r)] = parent.pop(key)
        elif kind == "add" and isinstance(parent, dict):
            parent[f"extra{r % 7}"] = value
        elif kind == "add" and isinstance(parent, list):
            parent.append(value)
    return d


def check_manifest_tree(doc: dict, ops, root: Path) -> str:
    from geocd.io.manifest import parse_manifest

    return _outcome(parse_manifest, mutate_tree(doc, ops), root, root / "scene.yaml")


def check_manifest_text(text: bytes, mutation, folder: Path) -> str:
    from geocd.io.manifest import load_manifest

    p = folder / "scene.yaml"
    p.write_bytes(mutate_bytes(text, mutation))
    return _outcome(load_manifest, p)


# ------------------------------------------------------------------------------------------------------------
# DEM GeoTIFFs (tags and pixels) through read_dem
# ------------------------------------------------------------------------------------------------------------
def check_dem_bytes(data: bytes, mutation, folder: Path) -> str:
    from geocd.io.raster import read_dem

    p = folder / "dem.tif"
    p.write_bytes(mutate_bytes(data, mutation))
    for side in folder.glob("dem.tif.*"):
        side.unlink()
    return _outcome(read_dem, p)


# ------------------------------------------------------------------------------------------------------------
# RPC metadata values (GDAL's RPC domain, here in an .aux.xml beside an image without RPC tags)
# ------------------------------------------------------------------------------------------------------------
RPC_SCALARS = (
    "LINE_OFF",
    "SAMP_OFF",
    "LAT_OFF",
    "LONG_OFF",
    "HEIGHT_OFF",
    "LINE_SCALE",
    "SAMP_SCALE",
    "LAT_SCALE",
    "LONG_SCALE",
    "HEIGHT_SCALE",
)
RPC_LISTS = ("LINE_NUM_COEFF", "LINE_DEN_COEFF", "SAMP_NUM_COEFF", "SAMP_DEN_COEFF")
_NUM_TEXT = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-1e4, 1e4).map(lambda v: f"{v:.6g}"),
    st.sampled_from(
        [
            "abc",
            "",
            " ",
            "1e308",
            "-1e308",
            "95",
            "400",
            "1e300",
            "0",
            "12 pixels",
            "1,5",
            "0x10",
            "nan",
            "inf",
            "+",
            "1e",
            "١٢",
        ]
    ),
    st.text(max_size=8),
)
rpc_tag_edits = st.dictionaries(st.sampled_from(RPC_SCALARS + RPC_LISTS), _NUM_TEXT, min_size=1, max_size=4)


def rpc_tags_of(model) -> dict[str, str]:
    """GDAL's RPC metadata domain (strings) of a model."""
    return {str(k): str(v) for k, v in model.to_rasterio().to_gdal().items()}


def check_rpc_tags(image: Path, tags: dict[str, str], edits: dict[str, str]) -> str:
    """Write ``tags`` with ``edits`` into ``image``'s .aux.xml; read the RPC; an accepted model must be usable."""
    from xml.sax.saxutils import escape

    from geocd.io.rpc import check_rpc_plausible, load_rpc_for_image

    t = dict(tags)
    for k, v in edits.items():
        if k in RPC_LISTS:  # one coefficient replaced
            vals = t[k].split()
            vals[len(v) % len(vals)] = v
            t[k] = " ".join(vals)
        else:
            t[k] = v
    items = "".join(f'<MDI key="{escape(k)}">{escape(v)}</MDI>' for k, v in t.items())
    Path(f"{image}.aux.xml").write_text(
        f'<PAMDataset><Metadata domain="RPC">{items}</Metadata></PAMDataset>', encoding="utf-8"
    )
    try:
        m = load_rpc_for_image(image)
    except GeoCDError as exc:
        return type(exc).__name__
    check_rpc_plausible(m)
    c, r = m.project(m.lon_off, m.lat_off, m.height_off)
    assert np.isfinite(c) and np.isfinite(r)
    return "ok"


def dump_yaml(doc: dict) -> bytes:
    buf = io.StringIO()
    yaml.safe_dump(json.loads(json.dumps(doc)), buf, sort_keys=False)
    return buf.getvalue().encode()


# ------------------------------------------------------------------------------------------------------------
# self-consistency models (JSON), frame-camera sidecars, RPC text files: what a reader accepts must be usable
# ------------------------------------------------------------------------------------------------------------
def _use_model(path: Path) -> None:
    from geocd.consistency import SelfConsistencyModel

    m = SelfConsistencyModel.load(path)
    pv = m.pvalue(np.array([0.0, 0.5, 3.0, 1e6]), np.array([-1.0, 0.0, 1.0, 5.0]))
    assert np.all((pv >= 0) & (pv <= 1)), pv
    for c in m.confidences:
        m.threshold(np.array([0.0, 1.0]), c)
    if m.has_region_test:
        conf = m.region_confidence(np.array([0.0, 10.0]))
        assert np.all((conf >= 0) & (conf <= 100)), conf


def check_model_tree(doc: dict, ops, folder: Path) -> str:
    p = Path(folder) / "model.json"
    p.write_text(json.dumps(mutate_tree(doc, ops), allow_nan=True))
    return _outcome(_use_model, p)


def check_model_bytes(data: bytes, mutation, folder: Path) -> str:
    p = Path(folder) / "model.json"
    p.write_bytes(mutate_bytes(data, mutation))
    return _outcome(_use_model, p)


def _use_camera(read, path: Path) -> None:
    cam = read(path)
    lon, lat, h = getattr(cam, "lon_off", None), getattr(cam, "lat_off", None), getattr(cam, "height_off", None)
    if lon is None:  # a frame camera: a point 100 m ahead on its optical axis (wherever the camera looks)
        x, y, z = np.asarray(cam.position, float) + cam.rotation @ np.array([0.0, 0.0, 100.0])
        c, r = cam.project_world(x, y, z)
    else:
        c, r = cam.project(lon, lat, h)
    assert np.all(np.isfinite(c)) and np.all(np.isfinite(r)), (c, r)


def check_frame_sidecar(doc: dict, ops, folder: Path) -> str:
    from geocd.io.frame import read_frame_sidecar

    p = Path(folder) / "img.json"
    p.write_text(json.dumps(mutate_tree(doc, ops), allow_nan=True))
    return _outcome(_use_camera, read_frame_sidecar, p)


def check_rpc_file(name: str, data: bytes, mutation, folder: Path) -> str:
    from geocd.io.rpc import read_rpc

    p = Path(folder) / name
    p.write_bytes(mutate_bytes(data, mutation))
    return _outcome(_use_camera, lambda q: read_rpc(q, image_path=None), p)


def check_torch_bytes(data: bytes, mutation, folder: Path) -> str:
    """A PyTorch weights file (zip of a pickle and storages), mutated: read without PyTorch, never a code path."""
    from geocd.screen.cnn import load_weights

    p = Path(folder) / "w.pth"
    p.write_bytes(mutate_bytes(data, mutation))
    return _outcome(load_weights, p)
