"""The geocd Processing provider in real headless QGIS (qgis_process.bin and standalone PyQGIS; no mocks).

Skipped with a reason when QGIS is not installed (.ci/install_system.sh installs it). geocd runs as the plugin's
child process from the environment running these tests (GEOCD_EXECUTABLE).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from ..conftest import shared_data
from .compare import compare_trees
from .qgis_env import QGIS, QGIS_PROCESS, REPO, geocd_executable, qgis_env, require_qgis

sys.path.insert(0, str(REPO / "qgis_plugin"))
from geocd_qgis import specs  # noqa: E402

pytestmark = pytest.mark.qgis


@pytest.fixture(scope="module")
def qgis(tmp_path_factory) -> QGIS:
    require_qgis()
    return QGIS(tmp_path_factory.mktemp("qgis_profile"))


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """geocd on the command line, in the environment its QGIS child gets (GDAL_PAM_ENABLED=NO, see qgis_env)."""
    env = {**os.environ, "GDAL_PAM_ENABLED": "NO"}
    return subprocess.run([geocd_executable(), *args], capture_output=True, text=True, cwd=cwd, timeout=900, env=env)


@pytest.mark.slow
def test_provider_loads_and_lists_every_algorithm(qgis):
    r = qgis.process("plugins")
    assert "* geocd_qgis" in r.stdout, r.stdout  # enabled
    r = qgis.process("list")
    assert r.returncode == 0, r.stderr
    listed = {line.split("\t")[1] for line in r.stdout.splitlines() if line.startswith("\tgeocd:")}
    expected = {f"geocd:{a.name}" for a in specs.active()}
    assert listed == expected, f"listed {sorted(listed)}, table {sorted(expected)}"
    assert "\ngeocd\n" in r.stdout  # the provider's own group


@pytest.mark.parametrize("alg", ["stereo", "change", "runlayers"])
@pytest.mark.slow
def test_help_prints_parameters(qgis, alg):
    r = qgis.process("help", f"geocd:{alg}")
    assert r.returncode == 0, r.stderr
    spec = specs.spec(alg)
    for p in spec.params:
        assert f"\n{p.name}: " in r.stdout, f"{p.name} missing from help:\n{r.stdout}"
    for o in spec.outputs:
        assert f"\n{o.name}: " in r.stdout
    assert spec.short_help[:60] in r.stdout


@pytest.mark.slow
def test_run_in_qgis_matches_cli(qgis, tmp_path):
    """`qgis_process run geocd:synth` writes the same products as `geocd synth` with the same options."""
    cli_out, qgis_out = tmp_path / "cli", tmp_path / "qgis"
    r = _cli(
        "--progress",
        "none",
        "synth",
        "--tiny",
        "--seed",
        "3",
        "--supersample",
        "1",
        "--n-aerial",
        "0",
        "--out",
        str(cli_out),
    )
    assert r.returncode == 0, r.stderr
    r, doc = qgis.run_json(
        "geocd:synth", {"TINY": "true", "SEED": 3, "SUPERSAMPLE": 1, "N_AERIAL": 0, "OUTPUT": str(qgis_out)}
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    res = doc["results"]
    assert res["OUTPUT"] == str(qgis_out)
    assert res["SCENE"] == str(qgis_out / "scene.yaml") and Path(res["REPORT"]).is_file()
    diffs = compare_trees(cli_out, qgis_out)
    assert not diffs, "\n".join(diffs)


@pytest.mark.slow
def test_zip_installs_into_a_profile_and_finds_geocd(tmp_path):
    """`geocd plugin-zip`, unzipped into a QGIS profile's plugins folder (what "Install from ZIP" does): the provider
    loads and finds geocd through the zip's environment.json (no PATH, no GEOCD_EXECUTABLE, not in a checkout)."""
    import zipfile

    require_qgis()
    zpath = tmp_path / "geocd_qgis.zip"
    r = _cli("plugin-zip", "--out", str(zpath))
    assert r.returncode == 0, r.stderr
    profile = tmp_path / "profile"
    plugins_dir = profile / "profiles" / "default" / "python" / "plugins"
    plugins_dir.mkdir(parents=True)
    with zipfile.ZipFile(zpath) as zf:
        zf.extractall(plugins_dir)
    env = qgis_env(profile)
    for k in ("QGIS_PLUGINPATH", "GEOCD_EXECUTABLE"):
        env.pop(k)
    env["PATH"] = "/usr/bin:/bin"
    env["HOME"] = str(tmp_path)  # no ~/.venvs/geocd and the like

    def qp(*args):
        return subprocess.run([str(QGIS_PROCESS), *args], env=env, capture_output=True, text=True, timeout=300)

    assert qp("plugins", "enable", "geocd_qgis").returncode == 0
    r = qp("run", "geocd:info", "--", f"INPUT={REPO / 'sample_aoi' / 'scene.yaml'}")
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert f"{geocd_executable()} --progress json info" in r.stdout
    assert "scene 'sample_aoi'" in r.stdout


@pytest.mark.slow
def test_executable_from_processing_settings(tmp_path):
    """Processing ▸ Options ▸ Providers ▸ geocd ▸ "geocd executable" wins over $GEOCD_EXECUTABLE; a Python
    interpreter there runs `python -m geocd`."""
    require_qgis()
    q = QGIS(tmp_path / "profile")
    ini = tmp_path / "profile" / "profiles" / "default" / "QGIS" / "QGIS3.ini"
    text = ini.read_text(encoding="utf-8") if ini.exists() else ""
    ini.parent.mkdir(parents=True, exist_ok=True)
    ini.write_text(text + f"\n[Processing]\nConfiguration\\GEOCD_EXECUTABLE={sys.executable}\n", encoding="utf-8")
    q.env["GEOCD_EXECUTABLE"] = str(tmp_path / "not" / "geocd")
    r = q.process("run", "geocd:info", "--", f"INPUT={REPO / 'sample_aoi' / 'scene.yaml'}")
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert f"{sys.executable} -m geocd --progress json info" in r.stdout
    assert "scene 'sample_aoi'" in r.stdout


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("tiny") / "scene"
    r = _cli(
        "--progress",
        "none",
        "synth",
        "--tiny",
        "--seed",
        "5",
        "--supersample",
        "1",
        "--n-aerial",
        "0",
        "--out",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    return out / "scene.yaml"


@pytest.mark.slow
def test_probchange_in_qgis_matches_cli_and_loads_styled_layers(qgis, tmp_path, tiny_scene):
    """`geocd:probchange` on a tiny synthetic scene: the CLI's change layers, loaded styled."""
    cli_out, qgis_out = tmp_path / "cli", tmp_path / "qgis"
    r = _cli("--progress", "none", "probchange", str(tiny_scene), "--out", str(cli_out))
    assert r.returncode == 0, r.stderr[-3000:]
    rep = qgis.pyqgis("run", "geocd:probchange", f"MANIFEST={tiny_scene}", f"OUTPUT={qgis_out}")
    assert rep.get("ok"), rep
    diffs = compare_trees(cli_out, qgis_out)
    assert not diffs, "\n".join(diffs)
    loaded = {d["output"]: d for d in rep["loaded"]}
    assert set(loaded) == {"PROBABILITY", "CHANGE_MASK", "CHANGES"}, loaded
    assert loaded["PROBABILITY"]["renderer"] == "singlebandpseudocolor"
    assert loaded["CHANGE_MASK"]["renderer"] == "paletted"
    assert loaded["CHANGES"]["renderer"] == "categorizedSymbol"


@pytest.mark.slow
def test_error_carries_geocds_message(qgis, tmp_path):
    """A bad input: the QgsProcessingException says what geocd says on the command line."""
    bad = tmp_path / "scene.yaml"
    bad.write_text("epochs: [unclosed\n")
    r = _cli("stereo", str(bad), "--out", str(tmp_path / "cli"))
    assert r.returncode != 0
    cli_message = r.stderr[r.stderr.index("geocd: error: ") + len("geocd: error: ") :].strip()
    rep = qgis.pyqgis("error", "geocd:stereo", f"MANIFEST={bad}", f"OUTPUT={tmp_path / 'qgis'}")
    assert rep.get("exception") == "QgsProcessingException", rep
    assert rep["message"] == cli_message
    assert rep["pid_alive"] is False
    # qgis_process reports it too, with a non-zero exit
    r = qgis.process("run", "geocd:stereo", "--", f"MANIFEST={bad}", f"OUTPUT={tmp_path / 'qgis2'}")
    assert r.returncode != 0 and cli_message in r.stdout + r.stderr


@pytest.mark.slow
def test_cancel_kills_child_and_leaves_no_partial_output(qgis, tmp_path):
    out = tmp_path / "cancelled"
    # 8x8 rays per pixel: a ~30 s job (plain tiny takes ~1 s and can finish before the cancel lands)
    rep = qgis.pyqgis("cancel", "geocd:synth", "0.1", "TINY=true", "SUPERSAMPLE=8", f"OUTPUT={out}")
    assert rep.get("exception") == "QgsProcessingException" and "cancelled" in rep["message"], rep
    assert rep["pid"] and rep["pid_alive"] is False
    assert rep["stop_after_cancel_s"] < 5.0
    assert 10 <= rep["max_progress"] < 100
    assert not out.exists(), f"partial output left: {sorted(p.name for p in out.rglob('*'))}"


@pytest.mark.realdata
@pytest.mark.slow
def test_demdiff_in_qgis_matches_cli_and_loads_styled_layers(qgis, tmp_path):
    """`geocd:demdiff` on two Mount St Helens DEMs: the CLI's products, loaded styled (not default grey)."""
    dems = shared_data("usgs_msh_dome_dems", "geotiff_utm10n")
    a, b = dems / "2.tif", dems / "27.tif"
    cli_out, qgis_out = tmp_path / "cli", tmp_path / "qgis"
    r = _cli("--progress", "none", "demdiff", str(a), str(b), "--out", str(cli_out))
    assert r.returncode == 0, r.stderr[-3000:]
    rep = qgis.pyqgis("run", "geocd:demdiff", f"DEM_A={a}", f"DEM_B={b}", f"OUTPUT={qgis_out}")
    assert rep.get("ok"), rep
    diffs = compare_trees(cli_out, qgis_out)
    assert not diffs, "\n".join(diffs)
    loaded = {d["output"]: d for d in rep["loaded"]}
    assert set(loaded) == {"DH", "SIGNIFICANCE", "CHANGE_MASK", "CHANGES"}, loaded
    assert all(d["valid"] for d in loaded.values()), loaded
    assert loaded["DH"]["renderer"] == "singlebandpseudocolor"
    assert loaded["CHANGE_MASK"]["renderer"] == "paletted"
    assert loaded["CHANGES"]["renderer"] == "categorizedSymbol" and loaded["CHANGES"]["features"] > 0
    assert rep["results"]["DH"] == str(qgis_out / "demdiff_dh.tif")


@pytest.mark.slow
def test_change_from_layers_on_sample_aoi_matches_cli(qgis, tmp_path, sample_aoi):
    """`geocd:runlayers` on a 60 m crop of sample_aoi (3 + 3 satellite images, prior DEM, footprints): the scene
    manifest the plugin writes, run by `geocd run`, gives the same layers; QGIS loads them styled."""
    img = sample_aoi / "images"
    qgis_out, cli_out = tmp_path / "qgis", tmp_path / "cli"
    params = [
        *(f"IMAGES_A={img / f'A_sat{k}.tif'}" for k in (1, 2, 3)),
        *(f"IMAGES_B={img / f'B_sat{k}.tif'}" for k in (1, 2, 3)),
        f"DEM={sample_aoi / 'truth' / 'dem_prior.tif'}",
        "DEM_DATUM=1",
        f"FOOTPRINTS={sample_aoi / 'truth' / 'footprints_all.gpkg'}",
        "AOI=374364,374424,4824264,4824324 [EPSG:32631]",
        f"OUTPUT={qgis_out}",
    ]
    rep = qgis.pyqgis("run", "geocd:runlayers", *params)
    assert rep.get("ok"), rep
    manifest = qgis_out / "scene_from_qgis.json"
    assert rep["results"]["SCENE_MANIFEST"] == str(manifest)
    r = _cli("--progress", "none", "run", str(manifest), "--out", str(cli_out))
    assert r.returncode == 0, r.stderr[-3000:]
    diffs = compare_trees(cli_out, qgis_out, ignore=(".png", "scene_from_qgis.json"))
    assert not diffs, "\n".join(diffs)
    loaded = {d["name"]: d for d in rep["loaded"]}
    assert all(d["valid"] for d in loaded.values()), loaded
    assert loaded["Buildings by change class"]["renderer"] == "categorizedSymbol"
    assert loaded["Buildings by change class"]["features"] > 0
    assert loaded["Changed regions"]["renderer"] == "categorizedSymbol"
    assert loaded["Change mask (raised / lowered / unchanged)"]["renderer"] == "paletted"
