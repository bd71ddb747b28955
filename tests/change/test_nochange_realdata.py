"""Real scenes where nothing changed: two pairs of one date given as two epochs (docs/kahramanmaras.md, "Against
buildings marked by eye"). Every building the layer calls changed would be a false alarm."""

import shutil

import pytest

from tests.conftest import REPO, shared_data

pytestmark = [pytest.mark.realdata, pytest.mark.slow]

MANIFEST = """geocd_manifest: 1
name: marseille_nochange
scene_class: urban-dense
epochs:
  - name: a
    images:
      - path: {d}/img_01.tif
      - path: {d}/img_02.tif
  - name: b
    images:
      - path: {tmp}/img_02_copy.tif
      - path: {d}/img_03.tif
"""


def test_marseille_one_date_as_two_epochs_has_no_changed_building(tmp_path):
    """The s2p Marseille triplet (one date): img_01 + img_02 against img_02 (a copy: the manifest refuses one file
    in two epochs) + img_03, with the example's scene-class model. Measured: 0.08 % of observed cells flagged at
    99 %, 197 buildings unchanged, 34 unobserved, none changed."""
    from geocd.change.building_layer import CHANGED
    from geocd.pipeline import RunConfig, run

    d = shared_data("s2p_pleiades", "input_triplet")
    shutil.copy(d / "img_02.tif", tmp_path / "img_02_copy.tif")
    (tmp_path / "scene.yaml").write_text(MANIFEST.format(d=d, tmp=tmp_path))
    model = REPO / "examples" / "kahramanmaras" / "marseille_urban_model.json"
    res = run(tmp_path / "scene.yaml", out_dir=tmp_path / "out", config=RunConfig(model_path=str(model)))
    r, b = res["result"], res["buildings"]
    flagged = float((r.changed_at(99.0) != 0)[r.observed].mean())
    assert flagged < 0.003, flagged  # 0.0008
    assert 170 <= (b["class"] == "unchanged").sum() <= 225  # 197
    assert not b["class"].isin(CHANGED).any(), b[b["class"].isin(CHANGED)][["class", "area_m2", "rule"]]
    assert res["summary"]["buildings"]["volume_lost_m3"] == 0.0
