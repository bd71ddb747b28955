"""Running real headless QGIS from the tests: ``qgis_process.bin`` and standalone PyQGIS scripts.

Facts (Debian 12, QGIS 3.22): call ``/usr/bin/qgis_process.bin`` (the ``qgis_process`` wrapper fails on the
QGIS_OPTS of /etc/default/qgis) with ``QT_QPA_PLATFORM=offscreen``, ``QGIS_PLUGINPATH`` = the plugin's parent
folder and ``QGIS_CUSTOM_CONFIG_PATH`` = a throw-away profile. PyQGIS scripts run under the system python
(/usr/bin/python3, python3-qgis), never geocd's venv: geocd itself runs as the plugin's child process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PLUGIN_PARENT = REPO / "qgis_plugin"
PLUGIN_NAME = "geocd_qgis"
QGIS_PROCESS = Path(os.environ.get("GEOCD_QGIS_PROCESS", "/usr/bin/qgis_process.bin"))
SYSTEM_PYTHON = Path(os.environ.get("GEOCD_QGIS_PYTHON", "/usr/bin/python3"))
PYQGIS_SCRIPT = Path(__file__).with_name("pyqgis_run.py")


def geocd_executable() -> str:
    """The geocd under test: the one beside the interpreter running pytest."""
    exe = Path(sys.executable).parent / "geocd"
    return str(exe) if exe.is_file() else f"{sys.executable}"


def require_qgis() -> None:
    if not QGIS_PROCESS.is_file():
        pytest.skip(
            f"QGIS is not installed ({QGIS_PROCESS} is absent): run .ci/install_system.sh "
            "(apt-get install qgis python3-qgis) to run the QGIS plugin tests"
        )


def qgis_env(profile: Path) -> dict:
    env = {
        k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "QGIS_PLUGINPATH")
    }
    env.update(
        {
            "QT_QPA_PLATFORM": "offscreen",
            "QGIS_PLUGINPATH": str(PLUGIN_PARENT),
            "QGIS_CUSTOM_CONFIG_PATH": str(profile),
            "GEOCD_EXECUTABLE": geocd_executable(),
            "XDG_RUNTIME_DIR": str(profile / "xdg"),
            "PYTHONDONTWRITEBYTECODE": "1",
            # QGIS computes statistics of raster parameter layers and GDAL would store them beside the
            # inputs (.aux.xml in sample_aoi/, ../shared/data): keep the inputs untouched
            "GDAL_PAM_ENABLED": "NO",
        }
    )
    (profile / "xdg").mkdir(parents=True, exist_ok=True, mode=0o700)
    return env


class QGIS:
    """A throw-away QGIS profile with the geocd plugin enabled."""

    def __init__(self, profile: Path):
        self.profile = profile
        self.env = qgis_env(profile)
        r = self.process("plugins", "enable", PLUGIN_NAME)
        if r.returncode != 0:
            raise RuntimeError(f"qgis_process plugins enable {PLUGIN_NAME} failed:\n{r.stdout}\n{r.stderr}")

    def process(self, *args: str, timeout: float = 600, cwd: Path | None = None) -> subprocess.CompletedProcess:
        return subprocess.run(
            [str(QGIS_PROCESS), *args],
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout,
            cwd=cwd,
            stdin=subprocess.DEVNULL,
        )

    def run_json(self, alg: str, params: dict, timeout: float = 600) -> tuple[subprocess.CompletedProcess, dict]:
        """``qgis_process.bin --json run ALG -- K=V ...`` → (process, parsed JSON or {})."""
        args = ["--json", "run", alg, "--"] + [f"{k}={v}" for k, v in params.items()]
        r = self.process(*args, timeout=timeout)
        try:
            doc = json.loads(r.stdout[r.stdout.index("{") :]) if "{" in r.stdout else {}
        except ValueError:
            doc = {}
        return r, doc

    def pyqgis(self, *args: str, timeout: float = 600) -> dict:
        """Run tests/qgis/pyqgis_run.py under the system python; returns its JSON report (last stdout line)."""
        r = subprocess.run(
            [str(SYSTEM_PYTHON), str(PYQGIS_SCRIPT), *args],
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout,
            stdin=subprocess.DEVNULL,
        )
        lines = [l for l in r.stdout.splitlines() if l.startswith("{")]
        if not lines:
            raise AssertionError(
                f"pyqgis_run.py {' '.join(args)} printed no report (rc {r.returncode}):\n"
                f"{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
            )
        return json.loads(lines[-1])
