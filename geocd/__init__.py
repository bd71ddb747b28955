"""geocd: 3-D change detection from satellite (RPC) and aerial (frame) images, DEMs and footprints."""

__version__ = "0.1.0"

from .errors import GeoCDError  # noqa: E402,F401
