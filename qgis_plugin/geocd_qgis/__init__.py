"""geocd for QGIS: a Processing provider whose algorithms run the geocd CLI in geocd's own environment.

Only PyQGIS and the standard library are imported here; geocd itself (numpy,
numba, rasterio, pyproj...) runs in a child process (see ``runner.py``).
"""


def classFactory(iface):  # noqa: N802 - QGIS plugin entry point
    from .plugin import GeocdPlugin

    return GeocdPlugin(iface)
