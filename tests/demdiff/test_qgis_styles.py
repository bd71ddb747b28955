"""The demdiff layers open styled in real QGIS (3.22): categorized changes, diverging dh ramp centred on 0."""

import json
import os
import subprocess
from pathlib import Path

import pytest

from geocd.demdiff import dem_difference
from geocd.demdiff.products import write_demdiff_products

from .synthetic import pair

pytestmark = pytest.mark.qgis

SYSTEM_PYTHON = Path(os.environ.get("GEOCD_QGIS_PYTHON", "/usr/bin/python3"))

SCRIPT = r"""
import json, sys
from qgis.core import QgsApplication, QgsVectorLayer, QgsRasterLayer
QgsApplication.setPrefixPath("/usr", True)
app = QgsApplication([], False); app.initQgis()
d = sys.argv[1]
out = {}
v = QgsVectorLayer(f"{d}/demdiff_changes.gpkg|layername=changes", "changes", "ogr")
r = v.renderer()
out["changes"] = [v.isValid(), r.type(), [(c.value(), c.symbol().color().name()) for c in r.categories()]]
ras = QgsRasterLayer(f"{d}/demdiff_dh.tif", "dh")
ras.loadDefaultStyle()
rr = ras.renderer()
items = rr.shader().rasterShaderFunction().colorRampItemList()
out["dh"] = [rr.type(), rr.classificationMin(), rr.classificationMax(), [(i.value, i.color.name()) for i in items]]
m = QgsRasterLayer(f"{d}/demdiff_change_mask.tif", "m"); m.loadDefaultStyle()
s = QgsRasterLayer(f"{d}/demdiff_significance.tif", "s"); s.loadDefaultStyle()
out["others"] = [m.renderer().type(), s.renderer().type(), s.renderer().usesBands()]
print(json.dumps(out))
"""


@pytest.mark.slow
def test_layers_open_styled_in_qgis(tmp_path):
    if not SYSTEM_PYTHON.is_file():
        pytest.skip("no system python with PyQGIS")
    probe = subprocess.run([str(SYSTEM_PYTHON), "-c", "import qgis.core"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip("PyQGIS is not installed (apt-get install python3-qgis)")
    a, b, _ = pair((3.0, 0.0, 0.5), bump_m=20.0)
    r = dem_difference(a, b)
    write_demdiff_products(tmp_path, r, plots=False)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(
        QT_QPA_PLATFORM="offscreen",
        QGIS_CUSTOM_CONFIG_PATH=str(tmp_path / "profile"),
        XDG_RUNTIME_DIR=str(tmp_path / "xdg"),
    )
    (tmp_path / "xdg").mkdir(mode=0o700)
    (tmp_path / "q.py").write_text(SCRIPT)
    p = subprocess.run(
        [str(SYSTEM_PYTHON), str(tmp_path / "q.py"), str(tmp_path)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    valid, kind, cats = out["changes"]
    assert valid and kind == "categorizedSymbol"
    assert dict(cats) == {"1": "#d7191c", "-1": "#2c7bb6"}  # red raised, blue lowered
    kind, lo, hi, items = out["dh"]
    assert kind == "singlebandpseudocolor" and lo == -hi and hi > 0
    assert [i[0] for i in items][3] == 0 and items[0][1] == "#2166ac" and items[-1][1] == "#b2182b"
    assert out["others"] == ["paletted", "singlebandpseudocolor", [1]]
