"""The ``geocd`` Processing provider: its algorithms, icon, version and the "geocd executable" setting."""

from __future__ import annotations

from pathlib import Path

from qgis.core import QgsProcessingProvider
from qgis.PyQt.QtGui import QIcon

from . import locate, specs
from .algorithm import GeocdAlgorithm, configured_executable

ICON_PATH = Path(__file__).resolve().parent / "icons" / "geocd.svg"
SETTING_EXECUTABLE = "GEOCD_EXECUTABLE"


def provider_icon() -> QIcon:
    return QIcon(str(ICON_PATH))


def plugin_version() -> str:
    for line in (Path(__file__).resolve().parent / "metadata.txt").read_text(encoding="utf-8").splitlines():
        if line.startswith("version="):
            return line.split("=", 1)[1].strip()
    return "unknown"


class GeocdProvider(QgsProcessingProvider):
    def id(self):
        return "geocd"

    def name(self):
        return "geocd"

    def longName(self):  # noqa: N802
        return f"geocd 3-D change detection ({self.versionInfo()})"

    def icon(self):
        return provider_icon()

    def svgIconPath(self):  # noqa: N802
        return str(ICON_PATH)

    def versionInfo(self):  # noqa: N802
        # geocd's own version once a check has run it (never start a child process while QGIS starts up)
        geocd = locate.cached_version()
        return f"plugin {plugin_version()}" + (f", geocd {geocd}" if geocd else "")

    def load(self):
        try:
            from processing.core.ProcessingConfig import ProcessingConfig, Setting

            ProcessingConfig.settingIcons[self.name()] = self.icon()
            ProcessingConfig.addSetting(
                Setting(
                    self.name(),
                    SETTING_EXECUTABLE,
                    "geocd executable (the geocd script, or its environment's python; empty = search PATH and known "
                    "virtual environments)",
                    "",
                    valuetype=Setting.FILE,
                )
            )
            ProcessingConfig.readSettings()
        except ImportError:  # Processing's Python side absent
            pass
        self.refreshAlgorithms()
        return True

    def unload(self):
        try:
            from processing.core.ProcessingConfig import ProcessingConfig

            ProcessingConfig.removeSetting(SETTING_EXECUTABLE)
        except ImportError:
            pass

    def canBeActivated(self):  # noqa: N802
        return True

    def warningMessage(self):  # noqa: N802
        argv, msg = locate.check_geocd(configured_executable())
        return "" if argv is not None else msg.splitlines()[0]

    def loadAlgorithms(self):  # noqa: N802
        for spec in specs.ALGORITHMS:
            if not spec.pending:
                self.addAlgorithm(GeocdAlgorithm(spec))
