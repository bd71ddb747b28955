"""Headless install of the plugin from the repository file `geocd plugin-zip` writes (QGIS's own installer), then
`qgis_process run` of three algorithms from that installation (no QGIS_PLUGINPATH, no GEOCD_EXECUTABLE)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from .qgis_env import QGIS_PROCESS, REPO, geocd_executable, qgis_env, require_qgis

sys.path.insert(0, str(REPO / "qgis_plugin"))
from geocd_qgis import specs  # noqa: E402

pytestmark = pytest.mark.qgis


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "GDAL_PAM_ENABLED": "NO"}
    return subprocess.run(
        [geocd_executable(), *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=900,
        env=env,
        stdin=subprocess.DEVNULL,
    )


def _dems(folder: Path, n: int = 3) -> list[Path]:
    from geocd.io.raster import write_cog
    from tests.demdiff.synthetic import grid, pair

    g = grid(60, 70)
    paths = []
    for k in range(n - 1):
        a, b, _ = pair((0.0, 0.0, 0.0), noise_m=0.4, bump_m=6.0 * (k + 1), g=g, seed=10 + k)
        if k == 0:
            paths.append(write_cog(folder / "dem0.tif", a.height_m.astype(np.float32), g))
        paths.append(write_cog(folder / f"dem{k + 1}.tif", b.height_m.astype(np.float32), g))
    return paths


@pytest.mark.slow
def test_install_from_repository_then_run_three_algorithms(tmp_path):
    require_qgis()
    # 1. the repository: zip + plugins.xml
    repo = tmp_path / "repo"
    r = _cli("plugin-zip", "--out", f"{repo}/")
    assert r.returncode == 0, r.stderr
    xml = repo / "plugins.xml"
    doc = xml.read_text(encoding="utf-8")
    assert (
        "<pyqgis_plugin" in doc
        and "<file_name>geocd_qgis.0.1.0.zip</file_name>" in doc
        and (repo / "geocd_qgis.0.1.0.zip").as_uri() in doc
    )
    # 2. headless install with QGIS's installer into a fresh profile (one command)
    profile = tmp_path / "profile"
    r = _cli("plugin-install", str(xml), "--profile", str(profile), "--json")
    assert r.returncode == 0, r.stdout + r.stderr
    rep = json.loads(r.stdout)["summary"]
    installed = profile / "profiles" / "default" / "python" / "plugins" / "geocd_qgis"
    assert Path(rep["path"]) == installed and rep["version"] == "0.1.0"
    assert (installed / "metadata.txt").is_file() and (installed / "environment.json").is_file()
    # 3. QGIS sees it installed and enabled, with no plugin path and no hint where geocd is
    env = qgis_env(profile)
    for k in ("QGIS_PLUGINPATH", "GEOCD_EXECUTABLE"):
        env.pop(k)
    env["PATH"] = "/usr/bin:/bin"
    env["HOME"] = str(tmp_path)

    def qp(*args, timeout=600):
        return subprocess.run(
            [str(QGIS_PROCESS), *args],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
            cwd=tmp_path,
            stdin=subprocess.DEVNULL,
        )

    r = qp("plugins")
    assert "* geocd_qgis" in r.stdout, r.stdout  # "*" = enabled
    r = qp("list")
    listed = {line.split("\t")[1] for line in r.stdout.splitlines() if line.startswith("\tgeocd:")}
    assert listed == {f"geocd:{a.name}" for a in specs.active()}
    # 4. three algorithms
    img = REPO / "sample_aoi" / "images" / "A_sat1.tif"
    r = qp("run", "geocd:info", "--", f"INPUT={img}")
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "camera: rpc" in r.stdout and f"{geocd_executable()} --progress json info" in r.stdout

    dems = _dems(tmp_path)
    out = tmp_path / "demdiff"
    r = qp(
        "--json", "run", "geocd:demdiff", "--", f"DEM_A={dems[0]}", f"DEM_B={dems[1]}", f"OUTPUT={out}", "CONFIDENCE=99"
    )
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    res = json.loads(r.stdout[r.stdout.index("{") :])["results"]
    assert Path(res["DH"]).is_file() and Path(res["CHANGES"].split("|")[0]).is_file()
    assert json.loads((out / "demdiff_report.json").read_text())["confidence_level_pct"] == 99.0
    assert (out / "geocd_demdiff.log").is_file()

    out = tmp_path / "series"
    r = qp(
        "--json",
        "run",
        "geocd:demseries",
        "--",
        f"DEMS={dems[0]}",
        f"DEMS={dems[1]}",
        f"DEMS={dems[2]}",
        "DATES=2020-01-01,2021-01-01,2022-01-01",
        f"OUTPUT={out}",
    )
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    res = json.loads(r.stdout[r.stdout.index("{") :])["results"]
    assert Path(res["TABLE"]).is_file()
    rows = Path(res["TABLE"]).read_text().splitlines()
    assert len(rows) >= 3  # header + two intervals


def test_install_reports_a_missing_repository(tmp_path):
    r = _cli("plugin-install", str(tmp_path / "nowhere" / "plugins.xml"), "--profile", str(tmp_path / "p"))
    assert r.returncode == 2 and "does not exist" in r.stderr


def test_readme_and_docs_count_the_provider_algorithms():
    """README's "N algorithms" and the docs table match what the provider offers (`qgis_process list`)."""
    import re

    n = len(specs.active())
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    m = re.search(r"Processing toolbox with (\d+) algorithms", readme)
    assert m and int(m.group(1)) == n, f"README says {m.group(1) if m else '?'} algorithms, the provider has {n}"
    docs = (REPO / "docs" / "qgis.md").read_text(encoding="utf-8")
    rows = re.findall(r"^\| `geocd:(\w+)` \|", docs, re.M)
    assert len(rows) == len(set(rows)), sorted(r for r in set(rows) if rows.count(r) > 1)  # each listed once
    assert set(rows) == {a.name for a in specs.active()}, set(rows) ^ {a.name for a in specs.active()}
