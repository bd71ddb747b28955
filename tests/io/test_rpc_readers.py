"""RPC readers (geocd.io.rpc): every vendor format, sidecar discovery, crops, bad inputs.

Synthetic files are written from :func:`tests.camera.test_rpc.synthetic_rpc` in each format
(tiny writers below), so the parsers are exercised without real data; the realdata tests
read every RPC sample of ../shared/data and compare formats of the same scene. Property
tests (hypothesis) truncate and corrupt files: the reader must return a model or raise
RPCParseError, nothing else.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from geocd.camera import RPCModel
from geocd.camera.rpc import RPC00A_FROM_B
from geocd.errors import InputFileNotFoundError, RPCNotFoundError, RPCParseError
from geocd.io.rpc import detect_rpc_format, find_rpc_sidecar, load_rpc_for_image, read_rpc
from tests.camera.test_rpc import REAL_RPC_FILES, box_grid, synthetic_rpc
from tests.conftest import shared_data

_B_FROM_A = np.argsort(RPC00A_FROM_B)  # a[j] = b[_B_FROM_A[j]]

# ---------------------------------------------------------------------------------------
# writers: one synthetic model in every vendor format
# ---------------------------------------------------------------------------------------
_COEFS = (("LINE_NUM", "line_num"), ("LINE_DEN", "line_den"), ("SAMP_NUM", "samp_num"), ("SAMP_DEN", "samp_den"))
_NORMS = (
    ("LINE_OFF", "line_off"),
    ("SAMP_OFF", "samp_off"),
    ("LAT_OFF", "lat_off"),
    ("LONG_OFF", "lon_off"),
    ("HEIGHT_OFF", "height_off"),
    ("LINE_SCALE", "line_scale"),
    ("SAMP_SCALE", "samp_scale"),
    ("LAT_SCALE", "lat_scale"),
    ("LONG_SCALE", "lon_scale"),
    ("HEIGHT_SCALE", "height_scale"),
)
_UNITS = {"LINE": "pixels", "SAMP": "pixels", "LAT_": "degrees", "LONG": "degrees", "HEIG": "meters"}


def _coef(m: RPCModel, attr: str, order: str = "B") -> np.ndarray:
    c = getattr(m, attr)
    return c[_B_FROM_A] if order == "A" else c


def write_ikonos(m: RPCModel, path: Path) -> Path:
    lines = [f"{k}: {getattr(m, a):+.10f} {_UNITS[k[:4]]}" for k, a in _NORMS]
    for k, a in _COEFS:
        lines += [f"{k}_COEFF_{i + 1}: {v:+.16E}" for i, v in enumerate(getattr(m, a))]
    lines += ["ERR_BIAS: 0002.50 meters", "ERR_RAND: 0000.10 meters"]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_rpb(m: RPCModel, path: Path, order: str = "B") -> Path:
    names = {
        "line_off": "lineOffset",
        "samp_off": "sampOffset",
        "lat_off": "latOffset",
        "lon_off": "longOffset",
        "height_off": "heightOffset",
        "line_scale": "lineScale",
        "samp_scale": "sampScale",
        "lat_scale": "latScale",
        "lon_scale": "longScale",
        "height_scale": "heightScale",
    }
    out = [
        'satId = "WV02";',
        'bandId = "P";',
        f'SpecId = "RPC00{order}";',
        "BEGIN_GROUP = IMAGE",
        "\terrBias =   2.50;",
        "\terrRand =    0.10;",
    ]
    out += [f"\t{names[a]} = {getattr(m, a)!r};" for _, a in _NORMS]
    for k, a in (
        ("lineNumCoef", "line_num"),
        ("lineDenCoef", "line_den"),
        ("sampNumCoef", "samp_num"),
        ("sampDenCoef", "samp_den"),
    ):
        vals = ",\n\t\t\t".join(f"{v:+.15E}" for v in _coef(m, a, order))
        out.append(f"\t{k} = (\n\t\t\t{vals});")
    out += ["END_GROUP = IMAGE", "END;"]
    path.write_text("\n".join(out) + "\n")
    return path


def write_dg_xml(m: RPCModel, path: Path, *, one_list: bool = True, order: str = "B") -> Path:
    tags = {
        "line_off": "LINEOFFSET",
        "samp_off": "SAMPOFFSET",
        "lat_off": "LATOFFSET",
        "lon_off": "LONGOFFSET",
        "height_off": "HEIGHTOFFSET",
        "line_scale": "LINESCALE",
        "samp_scale": "SAMPSCALE",
        "lat_scale": "LATSCALE",
        "lon_scale": "LONGSCALE",
        "height_scale": "HEIGHTSCALE",
    }
    body = [f"<{t}>{getattr(m, a)!r}</{t}>" for a, t in tags.items()]
    for k, a in (
        ("LINENUMCOEF", "line_num"),
        ("LINEDENCOEF", "line_den"),
        ("SAMPNUMCOEF", "samp_num"),
        ("SAMPDENCOEF", "samp_den"),
    ):
        c = _coef(m, a, order)
        inner = (
            f"<{k}>{' '.join(repr(float(v)) for v in c)}</{k}>"
            if one_list
            else "".join(f"<{k}>{float(v)!r}</{k}>" for v in c)
        )
        body.append(f"<{k}List>{inner}</{k}List>")
    xml = (
        f'<?xml version="1.0" encoding="UTF-8"?>\n<isd><IMD><NUMROWS>{m.height}</NUMROWS>'
        f"<NUMCOLUMNS>{m.width}</NUMCOLUMNS><IMAGE><SATID>WV02</SATID></IMAGE></IMD>"
        f"<RPB><SATID>WV02</SATID><SPECID>RPC00{order}</SPECID><IMAGE><ERRBIAS>2.5</ERRBIAS>"
        f"<ERRRAND>0.1</ERRRAND>{''.join(body)}</IMAGE></RPB></isd>\n"
    )
    path.write_text(xml)
    return path


def write_dimap(m: RPCModel, path: Path) -> Path:
    """DIMAP v2 RPC_*.XML: 1-based pixel offsets; the Direct_Model is a dummy (not read)."""

    def block(order_names):
        return "".join(
            f"<{k}_COEFF_{i + 1}>{float(v)!r}</{k}_COEFF_{i + 1}>"
            for k, a in order_names
            for i, v in enumerate(getattr(m, a))
        )

    inv = block(
        [("SAMP_NUM", "samp_num"), ("SAMP_DEN", "samp_den"), ("LINE_NUM", "line_num"), ("LINE_DEN", "line_den")]
    )
    val = (
        f"<LONG_SCALE>{m.lon_scale!r}</LONG_SCALE><LONG_OFF>{m.lon_off!r}</LONG_OFF>"
        f"<LAT_SCALE>{m.lat_scale!r}</LAT_SCALE><LAT_OFF>{m.lat_off!r}</LAT_OFF>"
        f"<HEIGHT_SCALE>{m.height_scale!r}</HEIGHT_SCALE><HEIGHT_OFF>{m.height_off!r}</HEIGHT_OFF>"
        f"<SAMP_SCALE>{m.samp_scale!r}</SAMP_SCALE><SAMP_OFF>{m.samp_off + 1!r}</SAMP_OFF>"
        f"<LINE_SCALE>{m.line_scale!r}</LINE_SCALE><LINE_OFF>{m.line_off + 1!r}</LINE_OFF>"
    )
    xml = (
        '<?xml version="1.0" encoding="UTF-8" standalone="no"?>\n<Dimap_Document><Metadata_Identification>'
        '<METADATA_FORMAT version="2.15">DIMAP</METADATA_FORMAT><METADATA_PROFILE>PHR_SENSOR</METADATA_PROFILE>'
        "</Metadata_Identification><Rational_Function_Model><Resource_Reference><RESOURCE_ID>RPC00B</RESOURCE_ID>"
        "</Resource_Reference><Global_RFM><Direct_Model><SAMP_NUM_COEFF_1>0</SAMP_NUM_COEFF_1></Direct_Model>"
        f"<Inverse_Model>{inv}<ERR_BIAS_ROW>0.001</ERR_BIAS_ROW></Inverse_Model><RFM_Validity>"
        f"<Direct_Model_Validity_Domain><FIRST_ROW>1</FIRST_ROW><FIRST_COL>1</FIRST_COL>"
        f"<LAST_ROW>{m.height}</LAST_ROW><LAST_COL>{m.width}</LAST_COL></Direct_Model_Validity_Domain>"
        f"{val}</RFM_Validity></Global_RFM></Rational_Function_Model></Dimap_Document>\n"
    )
    path.write_text(xml)
    return path


def write_geom(m: RPCModel, path: Path, order: str = "B") -> Path:
    lines = [
        "adjustment_0.adj_param_0.center:  0",
        "bias_error:  2.5",
        f"height_off:  {m.height_off!r}",
        f"height_scale:  {m.height_scale!r}",
        f"lat_off:  {m.lat_off!r}",
        f"lat_scale:  {m.lat_scale!r}",
    ]
    for k, a in (
        ("line_den_coeff", "line_den"),
        ("line_num_coeff", "line_num"),
        ("samp_den_coeff", "samp_den"),
        ("samp_num_coeff", "samp_num"),
    ):
        lines += [f"{k}_{i:02d}:  {float(v)!r}" for i, v in enumerate(_coef(m, a, order))]
    lines += [
        f"line_off:  {m.line_off!r}",
        f"line_scale:  {m.line_scale!r}",
        f"long_off:  {m.lon_off!r}",
        f"long_scale:  {m.lon_scale!r}",
        f"number_lines:  {m.height}",
        f"number_samples:  {m.width}",
        f"polynomial_format:  {order}",
        "rand_error:  0.1",
        f"samp_off:  {m.samp_off!r}",
        f"samp_scale:  {m.samp_scale!r}",
        'support_data.band_name_list:  """P """',
        "type:  ossimPleiadesModel",
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_satnerf(m: RPCModel, path: Path) -> Path:
    rpc = {
        "row_offset": m.line_off,
        "col_offset": m.samp_off,
        "lat_offset": m.lat_off,
        "lon_offset": m.lon_off,
        "alt_offset": m.height_off,
        "row_scale": m.line_scale,
        "col_scale": m.samp_scale,
        "lat_scale": m.lat_scale,
        "lon_scale": m.lon_scale,
        "alt_scale": m.height_scale,
        "row_num": m.line_num.tolist(),
        "row_den": m.line_den.tolist(),
        "col_num": m.samp_num.tolist(),
        "col_den": m.samp_den.tolist(),
    }
    path.write_text(json.dumps({"img": "x.tif", "height": m.height, "width": m.width, "rpc": rpc, "min_alt": 0}))
    return path


def write_orthority(m: RPCModel, path: Path, names=("a.tif", "b.tif")) -> Path:
    import yaml

    rpc = {
        "height_off": m.height_off,
        "height_scale": m.height_scale,
        "lat_off": m.lat_off,
        "lat_scale": m.lat_scale,
        "line_den_coeff": m.line_den.tolist(),
        "line_num_coeff": m.line_num.tolist(),
        "line_off": m.line_off,
        "line_scale": m.line_scale,
        "long_off": m.lon_off,
        "long_scale": m.lon_scale,
        "samp_den_coeff": m.samp_den.tolist(),
        "samp_num_coeff": m.samp_num.tolist(),
        "samp_off": m.samp_off,
        "samp_scale": m.samp_scale,
        "err_bias": 2.5,
        "err_rand": 0.1,
    }
    doc = {}
    for k, name in enumerate(names):
        r = dict(rpc, line_off=m.line_off + 100 * k)  # entries differ so the selection is visible
        doc[name] = {"im_size": [m.width, m.height], "rpc": r}
    path.write_text(yaml.safe_dump(doc, default_flow_style=None))
    return path


def write_geocd_json(m: RPCModel, path: Path) -> Path:
    path.write_text(json.dumps(m.to_dict()))
    return path


def write_geocd_yaml(m: RPCModel, path: Path) -> Path:
    import yaml

    path.write_text(yaml.safe_dump(m.to_dict()))
    return path


def write_tif(m: RPCModel | None, path: Path, *, transform=None, width=64, height=48) -> Path:
    import rasterio
    from affine import Affine

    profile = dict(driver="GTiff", width=width, height=height, count=1, dtype="uint8")
    if m is not None:
        profile["rpcs"] = m.to_rasterio()
    if transform is not None:
        profile["transform"] = Affine(*transform)
    import warnings

    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path, "w", **profile) as ds:
            ds.write(np.zeros((1, height, width), np.uint8))
    return path


WRITERS = {
    "ikonos_rpc.txt": write_ikonos,
    "wv.RPB": write_rpb,
    "wv_a.RPB": lambda m, p: write_rpb(m, p, order="A"),
    "dg.XML": write_dg_xml,
    "dg_elements.XML": lambda m, p: write_dg_xml(m, p, one_list=False),
    "dg_a.XML": lambda m, p: write_dg_xml(m, p, order="A"),
    "RPC_PHR1A_TEST.XML": write_dimap,
    "scene.geom": write_geom,
    "scene_a.geom": lambda m, p: write_geom(m, p, order="A"),
    "satnerf.json": write_satnerf,
    "rpc_param.yaml": lambda m, p: write_orthority(m, p, names=("a.tif",)),
    "model.rpc.json": write_geocd_json,
    "model.rpc.yaml": write_geocd_yaml,
    "tags.tif": write_tif,
}
EXPECTED_FORMAT = {
    "ikonos_rpc.txt": "RPC text",
    "wv.RPB": "DigitalGlobe RPB",
    "wv_a.RPB": "RPC00A reordered",
    "dg.XML": "DigitalGlobe XML",
    "dg_elements.XML": "DigitalGlobe XML",
    "dg_a.XML": "RPC00A reordered",
    "RPC_PHR1A_TEST.XML": "DIMAP",
    "scene.geom": "polynomial_format B",
    "scene_a.geom": "polynomial_format A",
    "satnerf.json": "Sat-NeRF",
    "rpc_param.yaml": "orthority YAML",
    "model.rpc.json": "geocd JSON",
    "model.rpc.yaml": "geocd YAML",
    "tags.tif": "GeoTIFF RPC tags",
}


@pytest.fixture(scope="module")
def model() -> RPCModel:
    return synthetic_rpc(seed=7)


@pytest.fixture(scope="module")
def written(model, tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("rpcfmt")
    return {name: w(model, d / name) for name, w in WRITERS.items()}


def _same_model(a: RPCModel, b: RPCModel, atol_px: float = 1e-9) -> None:
    np.testing.assert_allclose(a._coefs, b._coefs, rtol=1e-14, atol=1e-17)
    np.testing.assert_allclose(a._norm, b._norm, rtol=1e-14, atol=1e-12)
    lon, lat, h = box_grid(b, 5)
    ca, ra = a.project(lon, lat, h)
    cb, rb = b.project(lon, lat, h)
    assert np.max(np.hypot(ca - cb, ra - rb)) <= atol_px


# ---------------------------------------------------------------------------------------
# every format, synthetic
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(WRITERS))
def test_read_every_format(name, model, written):
    m = read_rpc(written[name], image_path=None)
    _same_model(m, model)
    assert str(written[name]) in m.source and EXPECTED_FORMAT[name] in m.source
    if name in ("ikonos_rpc.txt", "wv.RPB", "wv_a.RPB"):  # these formats carry no image size
        assert m.width is None
    else:
        assert (m.width, m.height) == ((64, 48) if name == "tags.tif" else (model.width, model.height))
    if name in ("ikonos_rpc.txt", "wv.RPB", "dg.XML", "rpc_param.yaml", "tags.tif"):
        assert m.err_bias == pytest.approx(2.5) and m.err_rand == pytest.approx(0.1)


@pytest.mark.parametrize("name", [n for n in WRITERS if not n.endswith(".tif")])
def test_format_is_detected_from_content(name, written, tmp_path, model):
    # same content, uninformative name: the reader still recognises it
    p = tmp_path / "camera.dat"
    p.write_bytes(written[name].read_bytes())
    assert detect_rpc_format(p) != ""
    _same_model(read_rpc(p), model)


def test_orthority_entry_selection(model, tmp_path):
    p = write_orthority(model, tmp_path / "rpc_param.yaml")
    assert read_rpc(p, image_path=write_tif(None, tmp_path / "b.tif")).line_off == model.line_off + 100
    with pytest.raises(RPCNotFoundError, match="none for c.tif"):
        read_rpc(p, image_path=write_tif(None, tmp_path / "c.tif"))
    two = write_orthority(model, tmp_path / "two.yaml")
    with pytest.raises(RPCNotFoundError, match="say which image"):
        read_rpc(two)


def test_dimap_offsets_are_made_zero_based(model, written):
    m = read_rpc(written["RPC_PHR1A_TEST.XML"])
    assert m.samp_off == model.samp_off and m.line_off == model.line_off


def test_gdal_writes_and_reads_our_tags(model, tmp_path):
    p = write_tif(model, tmp_path / "x.tif")
    m = load_rpc_for_image(p)
    _same_model(m, model)
    assert (m.width, m.height) == (64, 48) and "GeoTIFF RPC tags" in m.source


# ---------------------------------------------------------------------------------------
# sidecars and crops
# ---------------------------------------------------------------------------------------
SIDECAR_CASES = [
    ("{stem}_rpc.txt", write_ikonos),
    ("{stem}_RPC.TXT", write_ikonos),
    ("{stem}.RPB", write_rpb),
    ("{stem}.geom", write_geom),
    ("{stem}.XML", write_dg_xml),
    ("{stem}.json", write_satnerf),
    ("{stem}.rpc.json", write_geocd_json),
    ("RPC_{stem}.XML", write_dimap),
    ("RPC_PHR1B_P_201709281038393_SEN_PRG_FC_178609-001.XML", write_dimap),  # the folder's only RPC_*.XML
]


@pytest.mark.parametrize("pattern,writer", SIDECAR_CASES, ids=[p for p, _ in SIDECAR_CASES])
def test_sidecar_discovery(pattern, writer, model, tmp_path):
    image = write_tif(None, tmp_path / "IMG_scene_R1C1.tif")
    side = writer(model, tmp_path / pattern.format(stem=image.stem))
    assert find_rpc_sidecar(image) == side
    m = load_rpc_for_image(image)
    assert (m.width, m.height) == (64, 48)
    assert str(side) in m.source
    _same_model(m.replace(width=model.width, height=model.height), model)


def test_dimap_for_img_prefix(model, tmp_path):
    image = write_tif(None, tmp_path / "IMG_PHR1B_P_2017_R1C1.tif")
    side = write_dimap(model, tmp_path / "RPC_PHR1B_P_2017.XML")
    write_dimap(model, tmp_path / "RPC_OTHER.XML")  # two RPC_*.XML: only the matching name counts
    assert find_rpc_sidecar(image) == side


def test_ambiguous_or_foreign_sidecars_are_not_used(model, tmp_path):
    image = write_tif(None, tmp_path / "scene.tif")
    (tmp_path / "scene.xml").write_text("<gpx><trk/></gpx>")  # an XML that is not an RPC
    (tmp_path / "scene.json").write_text('{"name": "not an rpc"}')
    write_dimap(model, tmp_path / "RPC_A.XML")
    write_dimap(model, tmp_path / "RPC_B.XML")  # two candidates: refuse to guess
    assert find_rpc_sidecar(image) is None
    with pytest.raises(RPCNotFoundError) as exc:
        load_rpc_for_image(image)
    msg = str(exc.value)
    assert "scene_rpc.txt" in msg and "scene.rpb" in msg and "read_rpc" in msg


def test_tiles_other_than_r1c1_do_not_take_the_folder_rpc(model, tmp_path):
    image = write_tif(None, tmp_path / "IMG_X_R2C1.tif")
    write_dimap(model, tmp_path / "RPC_Y.XML")
    assert find_rpc_sidecar(image) is None


def test_tags_win_over_sidecar(model, tmp_path):
    image = write_tif(model, tmp_path / "s.tif")
    write_ikonos(model.cropped(10, 10), tmp_path / "s_rpc.txt")
    m = load_rpc_for_image(image)
    assert m.samp_off == model.samp_off


def test_pam_aux_xml_counts_as_tags(model, tmp_path):
    image = write_tif(None, tmp_path / "pam.tif")
    items = "".join(f'<MDI key="{k}">{v}</MDI>' for k, v in model.to_gdal_metadata().items())
    Path(f"{image}.aux.xml").write_text(f'<PAMDataset><Metadata domain="RPC">{items}</Metadata></PAMDataset>')
    m = load_rpc_for_image(image)
    assert ".aux.xml" in m.source
    _same_model(m.replace(width=model.width, height=model.height), model)


def test_gdal_metadata_readers_are_the_last_resort(model, tmp_path, monkeypatch):
    # a sidecar layout geocd's discovery would not know, but GDAL's metadata readers do
    import geocd.io.rpc as R

    image = write_tif(None, tmp_path / "last.tif", transform=(1, 0, 10, 0, 1, 20))
    write_rpb(model, tmp_path / "last.RPB")
    monkeypatch.setattr(R, "find_rpc_sidecar", lambda p: None)
    m = load_rpc_for_image(image)
    assert "GDAL's metadata readers" in m.source and "last.RPB" in m.source
    assert m.samp_off == model.samp_off - 10 and (m.width, m.height) == (64, 48)


def test_crop_geotransform_applies_offsets(model, tmp_path):
    # CNES/OTB crops: geotransform (1, 0, x0, 0, 1, y0) without CRS, full-scene RPC sidecar
    image = write_tif(None, tmp_path / "crop.tif", transform=(1, 0, 300, 0, 1, 200), width=40, height=30)
    write_geom(model, tmp_path / "crop.geom")
    m = load_rpc_for_image(image)
    assert (m.width, m.height) == (40, 30) and "cropped at col=300 row=200" in m.source
    lon, lat, h = box_grid(model, 4)
    c0, r0 = model.project(lon, lat, h)
    c1, r1 = m.project(lon, lat, h)
    np.testing.assert_allclose(c1, c0 - 300, atol=1e-9)
    np.testing.assert_allclose(r1, r0 - 200, atol=1e-9)
    m2 = read_rpc(tmp_path / "crop.geom", image_path=image, apply_crop=False)
    assert m2.samp_off == model.samp_off and m2.width == 40


def test_image_without_rpc_raises_not_found(tmp_path):
    image = write_tif(None, tmp_path / "plain.tif")
    with pytest.raises(RPCNotFoundError, match="no RPC"):
        load_rpc_for_image(image)
    with pytest.raises(RPCNotFoundError, match="no RPC metadata"):
        read_rpc(image)


def test_missing_files(tmp_path):
    with pytest.raises(InputFileNotFoundError):
        read_rpc(tmp_path / "nope_rpc.txt")
    with pytest.raises(InputFileNotFoundError):
        load_rpc_for_image(tmp_path / "nope.tif")


def test_cameras_module_uses_rpc_readers(model, tmp_path):
    from geocd.io.cameras import load_camera

    image = write_tif(None, tmp_path / "cam.tif")
    write_rpb(model, tmp_path / "cam.RPB")
    cam = load_camera(image)
    assert isinstance(cam, RPCModel) and cam.width == 64


# ---------------------------------------------------------------------------------------
# garbled files: RPCParseError naming the file and what is wrong
# ---------------------------------------------------------------------------------------
def _expect_parse_error(path: Path, *needles: str) -> None:
    with pytest.raises(RPCParseError) as exc:
        read_rpc(path)
    msg = str(exc.value)
    assert str(path) in msg, msg
    for n in needles:
        assert n in msg, msg


def test_missing_keys_are_named(model, written, tmp_path):
    text = written["ikonos_rpc.txt"].read_text()
    p = tmp_path / "cut_rpc.txt"
    p.write_text("\n".join(ln for ln in text.splitlines() if not ln.startswith(("LAT_SCALE", "SAMP_DEN_COEFF_7:"))))
    _expect_parse_error(p, "LAT_SCALE", "SAMP_DEN_COEFF_{7}")


def test_bad_values_are_named(written, tmp_path):
    p = tmp_path / "bad.RPB"
    p.write_text(written["wv.RPB"].read_text().replace("lineOffset = ", "lineOffset = x"))
    _expect_parse_error(p, "LINE_OFF", "not a number")
    p = tmp_path / "nan_rpc.txt"
    p.write_text(written["ikonos_rpc.txt"].read_text().replace("LONG_OFF: ", "LONG_OFF: nan #"))
    _expect_parse_error(p, "lon_off")


def test_an_implausible_coefficient_is_named_even_when_the_model_cannot_be_built(written, tmp_path, monkeypatch):
    """A coefficient of 1e300 may or may not make the model's affine start singular, by the last bits of the
    BLAS; either way the error names the coefficient, the cause."""
    p = tmp_path / "big_rpc.txt"
    p.write_text(written["ikonos_rpc.txt"].read_text().replace("SAMP_NUM_COEFF_2: ", "SAMP_NUM_COEFF_2: 1e300 #"))
    _expect_parse_error(p, "SAMP_NUM_COEFF_2=1e+300 is not a plausible coefficient")

    def singular(self):
        raise RPCParseError("the RPC does not map ground to image one-to-one (singular affine part)")

    monkeypatch.setattr(RPCModel, "_affine_start", singular)
    _expect_parse_error(p, "SAMP_NUM_COEFF_2=1e+300 is not a plausible coefficient")
    # a plausible model whose start fails keeps the constructor's own message
    _expect_parse_error(written["ikonos_rpc.txt"], "singular affine part")


@pytest.mark.parametrize(
    "content,needle",
    [
        ("", "not an RPC file"),
        ("hello world\n", "not an RPC file"),
        ("<Dimap_Document><Rational_Function_Model/></Dimap_Document>", "lacks"),
        ("<isd><IMD/></isd>", "XML file without an RPC"),
        ("<isd><RPB><IMAGE><LINEOFFSET>1</LINEOFFSET>", "not well-formed XML"),
        ("[1, 2, 3]", "not an RPC description"),
        ('{"rpc": {"row_offset": 1}}', "lacks"),
        ('{"rpc": ', "not valid JSON"),
        ("polynomial_format:  C\nline_num_coeff_00: 1\n", "polynomial_format"),
        ("a:\n  - [1, 2\n", "not valid YAML"),
    ],
)
def test_garbled_inputs(content, needle, tmp_path):
    p = tmp_path / "weird.dat"
    p.write_text(content)
    _expect_parse_error(p, needle)


def test_binary_garbage(tmp_path):
    p = tmp_path / "garbage.tif"
    p.write_bytes(b"II*\x00" + bytes(range(256)) * 4)
    _expect_parse_error(p, "GDAL cannot open")


# ---------------------------------------------------------------------------------------
# property tests: truncation and corruption never give anything but a model or RPCParseError
# ---------------------------------------------------------------------------------------
def _mutate(data: bytes, how: str, pos: float, payload: bytes, count: int, rnd: np.random.Generator) -> bytes:
    n = len(data)
    i = min(int(pos * n), n)
    if how == "truncate":
        return data[:i]
    if how == "insert":
        return data[:i] + payload + data[i:]
    if how == "delete":
        return data[:i] + data[i + count :]
    # flip `count` random bytes
    b = bytearray(data)
    for j in rnd.integers(0, max(n, 1), size=count):
        if n:
            b[j] = int(rnd.integers(0, 256))
    return bytes(b)


_mutations = st.tuples(
    st.sampled_from(["truncate", "insert", "delete", "flip"]),
    st.floats(0.0, 1.0),
    st.binary(min_size=1, max_size=12),
    st.integers(1, 40),
    st.integers(0, 2**32 - 1),
)


def _check_mutation(src: Path, tmp: Path, mutation, binary: bool) -> None:
    how, pos, payload, count, seed = mutation
    data = _mutate(src.read_bytes(), how, pos, payload, count, np.random.default_rng(seed))
    p = tmp / src.name
    p.write_bytes(data)
    try:
        m = read_rpc(p)
    except RPCParseError as exc:
        assert str(p) in str(exc)
        return
    except RPCNotFoundError:
        # a raster that lost its RPC tags, or an orthority file whose entry names were garbled
        assert binary or src.suffix in (".yaml", ".yml")
        return
    assert isinstance(m, RPCModel)
    m.project(m.lon_off, m.lat_off, m.height_off)  # a model that was accepted is usable


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from([n for n in WRITERS if not n.endswith(".tif")]), mutation=_mutations)
def test_property_corrupted_synthetic_files(name, mutation, written, tmp_path_factory):
    _check_mutation(written[name], tmp_path_factory.mktemp("mut"), mutation, binary=False)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(mutation=_mutations)
def test_property_corrupted_geotiff(mutation, written, tmp_path_factory):
    _check_mutation(written["tags.tif"], tmp_path_factory.mktemp("mut"), mutation, binary=True)


@pytest.mark.slow
@settings(max_examples=3000, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from(list(WRITERS)), mutation=_mutations)
def test_property_corrupted_synthetic_files_long(name, mutation, written, tmp_path_factory):
    _check_mutation(written[name], tmp_path_factory.mktemp("mut"), mutation, binary=name.endswith(".tif"))


_REAL_TEXT = [(d, f) for d, f in REAL_RPC_FILES if not f.lower().endswith((".tif", ".ntf"))]
_REAL_BINARY = [(d, f) for d, f in REAL_RPC_FILES if f.lower().endswith((".tif", ".ntf"))]


@pytest.mark.realdata
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(which=st.sampled_from(_REAL_TEXT), mutation=_mutations)
def test_property_corrupted_real_text_files(which, mutation, tmp_path_factory):
    _check_mutation(shared_data(*which), tmp_path_factory.mktemp("mut"), mutation, binary=False)


@pytest.mark.realdata
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    which=st.sampled_from(
        [
            w
            for w in _REAL_BINARY
            if w[1] in ("wv3_20.NTF", "qb2_basic1b.tif") or w[0] in ("rpc_samples/shareloc", "s2p_pleiades/input_pair")
        ]
    ),
    mutation=_mutations,
)
def test_property_corrupted_real_rasters(which, mutation, tmp_path_factory):
    _check_mutation(shared_data(*which), tmp_path_factory.mktemp("mut"), mutation, binary=True)


# ---------------------------------------------------------------------------------------
# real samples
# ---------------------------------------------------------------------------------------
_REAL_FORMAT = {
    ".TXT": "RPC text",
    ".txt": "RPC text",
    ".json": "Sat-NeRF/DFC2019 JSON",
    ".geom": "OSSIM .geom",
    ".tif": "GeoTIFF RPC tags",
    ".NTF": "NITF RPC00B TRE",
    ".yaml": "orthority YAML",
}


@pytest.mark.realdata
@pytest.mark.parametrize("folder,name", REAL_RPC_FILES, ids=[f"{d.split('/')[0]}/{f}" for d, f in REAL_RPC_FILES])
def test_read_real_sample(folder, name):
    p = shared_data(folder, name)
    m = read_rpc(p)
    assert isinstance(m, RPCModel) and str(p) in m.source
    suffix = p.suffix
    if suffix.lower() == ".xml":
        want = "DIMAP" if "RPC_" in name or name in ("rpc_PLEIADES.xml", "rpc_SPOT6.xml") else "DigitalGlobe XML"
    else:
        want = _REAL_FORMAT[suffix]
    assert want in m.source, m.source
    # the validity box is where the samples say the scenes are
    b = m.validity_box()
    assert b["lon"][0] < m.lon_off < b["lon"][1] and -90 < m.lat_off < 90


@pytest.mark.realdata
def test_real_known_values():
    ik = read_rpc(shared_data("rpc_samples/rpcm", "rpc_IKONOS.txt"))
    assert (ik.line_off, ik.samp_off, ik.lon_off, ik.height_scale) == (5124.0, 6334.0, -56.1722, 82.0)
    assert ik.err_bias == 3.31 and ik.line_num[0] == pytest.approx(-1.490910093701323e-03, rel=1e-15)
    wv1 = read_rpc(shared_data("rpc_samples/rpcm", "rpc_WV1.xml"))
    assert (wv1.line_off, wv1.lat_off, wv1.width, wv1.height) == (13413.0, 50.9491, 35180, 26828)
    sp6 = read_rpc(shared_data("rpc_samples/rpcm", "rpc_SPOT6.xml"))
    # Haiti: lon -72.27, lat 18.58 (the file's validity-domain FIRST_LON/FIRST_LAT are swapped; offsets are not)
    assert sp6.lon_off == pytest.approx(-72.26895693) and sp6.samp_off == 10975.5
    jax = read_rpc(shared_data("rpc_samples/rpcm", "JAX_068_001_RGB.json"))
    assert (jax.width, jax.height) == (746, 815) and jax.height_off == -21.0
    yml = read_rpc(shared_data("orthority_baviaans_aerial_qb2/rpc", "rpc_param.yaml"))
    tif = read_rpc(shared_data("orthority_baviaans_aerial_qb2/rpc", "qb2_basic1b.tif"))
    _same_model(yml, tif)
    assert (yml.width, yml.height) == (tif.width, tif.height) == (850, 1450)


def _max_px(a: RPCModel, b: RPCModel, n: int = 11) -> float:
    lon, lat, h = box_grid(b, n)
    ca, ra = a.project(lon, lat, h)
    cb, rb = b.project(lon, lat, h)
    return float(np.max(np.hypot(ca - cb, ra - rb)))


@pytest.mark.realdata
def test_real_shareloc_tags_geom_dimap_agree():
    d = "rpc_samples/shareloc"
    stem = "PHR1B_P_201709281038393_SEN_PRG_FC_178609-001"
    tags = read_rpc(shared_data(d, stem + ".tif"))
    geom = read_rpc(shared_data(d, stem + ".geom"))
    dimap = read_rpc(shared_data(d, "RPC_" + stem + ".XML"))
    # the DIMAP offsets are 1-based: after the -1 they equal GDAL's tags exactly
    assert dimap.samp_off == tags.samp_off == geom.samp_off == 19999.5
    assert _max_px(geom, tags) <= 1e-3 and _max_px(dimap, tags) <= 1e-3 and _max_px(dimap, geom) <= 1e-3
    # the other image of the pair is a different camera
    other = read_rpc(shared_data(d, "RPC_PHR1B_P_201709281038045_SEN_PRG_FC_178608-001.XML"))
    assert _max_px(other, tags) > 10


@pytest.mark.realdata
def test_real_ventoux_geom_crop_matches_dimap():
    d = "cnes_pleiades_ventoux"
    left = shared_data(d, "left_image.tif")
    xml = shared_data(d, "RPC_PHR1B_P_201308051042194_SEN_690908101-001.XML")
    geom_full = read_rpc(shared_data(d, "left_image.geom"))
    # the XML is the left image's: the .geom says image_id 690908101-001, as the XML's name does
    assert "image_id:  690908101-001" in shared_data(d, "left_image.geom").read_text()
    cam = load_rpc_for_image(left)  # .geom sidecar + crop offsets (5000, 5000) from the geotransform
    assert (cam.width, cam.height) == (500, 500) and "cropped at col=5000 row=5000" in cam.source
    assert cam.samp_off == geom_full.samp_off - 5000 and cam.line_off == geom_full.line_off - 5000
    cam_xml = read_rpc(xml, image_path=left)  # DIMAP with the same crop
    assert "cropped at col=5000 row=5000" in cam_xml.source
    assert _max_px(cam_xml, cam) <= 1e-3
    assert _max_px(read_rpc(xml), geom_full) <= 1e-3
    right = load_rpc_for_image(shared_data(d, "right_image.tif"))
    assert (right.width, right.height) == (498, 495) and "col=4915 row=5162" in right.source
    assert _max_px(cam_xml, right.cropped(0, 0)) > 10  # not the right image's RPC
    # the crop is where the images are: both crops see the documented overlap latitudes
    lon, lat = cam.localize(250.0, 250.0, 540.0)
    assert 44.20 < lat < 44.21 and 5.19 < lon < 5.20


@pytest.mark.realdata
@pytest.mark.parametrize(
    "folder,name",
    [
        ("s2p_pleiades/input_pair", "img_01.tif"),
        ("s2p_pleiades/input_pair", "img_02.tif"),
        ("s2p_pleiades/input_triplet", "img_01.tif"),
        ("s2p_pleiades/input_triplet", "img_02.tif"),
        ("s2p_pleiades/input_triplet", "img_03.tif"),
        ("rpc_samples/shareloc", "wv3_20.NTF"),
        ("orthority_baviaans_aerial_qb2/rpc", "qb2_basic1b.tif"),
    ],
)
def test_real_images_load_their_tags(folder, name):
    import rasterio

    p = shared_data(folder, name)
    m = load_rpc_for_image(p)
    with rasterio.open(p) as ds:
        assert (m.width, m.height) == (ds.width, ds.height)
    assert "cropped" not in m.source
    # the image centre localizes inside the RPC's validity box
    lon, lat = m.localize(m.width / 2, m.height / 2, m.height_off)
    b = m.validity_box()
    assert b["lon"][0] <= lon <= b["lon"][1] and b["lat"][0] <= lat <= b["lat"][1]
