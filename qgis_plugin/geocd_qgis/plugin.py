"""The plugin object QGIS creates: it only registers the Processing provider (no GUI of its own)."""

from __future__ import annotations

from qgis.core import QgsApplication


class GeocdPlugin:
    def __init__(self, iface=None):
        self.iface = iface
        self.provider = None

    def initProcessing(self):  # noqa: N802 - called by QGIS (also by qgis_process, which has no GUI)
        if self.provider is None:
            from .provider import GeocdProvider

            self.provider = GeocdProvider()
            QgsApplication.processingRegistry().addProvider(self.provider)

    def initGui(self):  # noqa: N802
        self.initProcessing()

    def unload(self):
        if self.provider is not None:
            QgsApplication.processingRegistry().removeProvider(self.provider)
            self.provider = None
