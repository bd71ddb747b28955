"""Orthoimages open stretched in real QGIS (3.22): a 16-bit grey ortho and an RGB one keep the 2–98 % stretch
written in their .qml sidecars (nested one element too deep, QGIS ignored it and drew 16-bit images black)."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from geocd.change.styles import write_raster_style
from geocd.geodesy import AOIGrid
from geocd.io.raster import write_cog
from geocd.ortho.pipeline import ortho_qml

from ..qgis.qgis_env import SYSTEM_PYTHON, qgis_env, require_qgis

pytestmark = pytest.mark.qgis

SCRIPT = r"""
import json, os, sys
from qgis.core import QgsApplication, QgsRasterLayer
QgsApplication.setPrefixPath("/usr", True)
app = QgsApplication([], False); app.initQgis()
out = {}
for name in sys.argv[1:]:
    lay = QgsRasterLayer(name, "o")
    r = lay.renderer()
    ces = ([r.contrastEnhancement()] if r.type() == "singlebandgray" else
           [r.redContrastEnhancement(), r.greenContrastEnhancement(), r.blueContrastEnhancement()])
    out[name] = [r.type(), [[c.minimumValue(), c.maximumValue(), int(c.contrastEnhancementAlgorithm())]
                            for c in ces]]
print(json.dumps(out))
os._exit(0)
"""


def _write(path, values, grid):
    observed = np.ones(grid.shape, bool)
    observed[:5] = False
    p = write_cog(path, {f"b{k + 1}": v for k, v in enumerate(values)}, grid, mask=observed)
    write_raster_style(p, ortho_qml(values, observed))
    return p, [np.percentile(v[observed], [2, 98]) for v in values]


def test_orthos_open_stretched_in_qgis(tmp_path):
    require_qgis()
    grid = AOIGrid.from_bounds(374200.0, 4824300.0, 374260.0, 4824340.0, 1.0, "EPSG:32631")
    rng = np.random.default_rng(3)
    grey = rng.integers(400, 1400, (1, *grid.shape)).astype(np.uint16)  # Pléiades-like 12-bit values
    rgb = rng.integers(20, 220, (3, *grid.shape)).astype(np.uint8)
    p_grey, st_grey = _write(tmp_path / "grey.tif", grey, grid)
    p_rgb, st_rgb = _write(tmp_path / "rgb.tif", rgb, grid)
    env = qgis_env(tmp_path / "profile")
    (tmp_path / "q.py").write_text(SCRIPT)
    p = subprocess.run(
        [str(SYSTEM_PYTHON), str(tmp_path / "q.py"), str(p_grey), str(p_rgb)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    kind, ces = out[str(p_grey)]
    assert kind == "singlebandgray"
    stretch_to_min_max = 1
    assert ces == [[pytest.approx(st_grey[0][0]), pytest.approx(st_grey[0][1]), stretch_to_min_max]]
    kind, ces = out[str(p_rgb)]
    assert kind == "multibandcolor"
    assert ces == [[pytest.approx(lo), pytest.approx(hi), stretch_to_min_max] for lo, hi in st_rgb]
