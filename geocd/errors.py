"""One hierarchy of errors for geocd.

Every error geocd raises on purpose is a :class:`GeoCDError`. Each subclass also
inherits the builtin that fits it (``ValueError``, ``FileNotFoundError``, ...), so
callers that already catch builtins keep working (rasterio's style).

Messages say what was wrong *and* how to fix it. The CLI prints the message and
exits non-zero without a traceback.
"""

from __future__ import annotations


class GeoCDError(Exception):
    """Base class of every error geocd raises on purpose."""

    #: exit code used by the CLI for this family of errors
    exit_code: int = 2


# --- input files and formats -------------------------------------------------
class InputFileNotFoundError(GeoCDError, FileNotFoundError):
    """A file named by the user (or by a manifest) does not exist."""


class UnsupportedFormatError(GeoCDError, ValueError):
    """A file exists but geocd cannot read that format."""


class UntrustedFileError(GeoCDError, PermissionError):
    """A file that could run code when loaded (a pickle) was not written by geocd here, nor trusted explicitly."""


# --- cameras ------------------------------------------------------------------
class CameraError(GeoCDError, ValueError):
    """Base for camera-model problems."""


class RPCNotFoundError(CameraError, LookupError):
    """An image has no RPC (no tags, no sidecar) and no other camera model."""


class RPCParseError(CameraError):
    """An RPC file or tag set is truncated, garbled or inconsistent."""


class FrameCameraError(CameraError):
    """A frame (pinhole) camera's interior/exterior orientation is invalid."""


class LocalizationError(CameraError, ArithmeticError):
    """Pixel-to-ground localization did not converge."""


class NoCameraError(CameraError, LookupError):
    """An image has neither a georeference nor a camera model."""


# --- geodesy, grids, datums ------------------------------------------------------
class CRSError(GeoCDError, ValueError):
    """A coordinate reference system is missing, invalid or incompatible."""


class VerticalDatumError(CRSError):
    """Heights are in a vertical datum geocd cannot convert (missing geoid grid)."""


class GridError(GeoCDError, ValueError):
    """An AOI grid is invalid, or rasters do not overlap it."""


class NoOverlapError(GridError):
    """Inputs that must overlap (images, DEMs, AOI) do not."""


# --- data content ------------------------------------------------------------------
class EmptyDataError(GeoCDError, ValueError):
    """A raster is entirely nodata, or a vector has no usable features."""


class ManifestError(GeoCDError, ValueError):
    """A scene manifest is invalid: missing keys, bad values, missing files."""


class ConfigError(GeoCDError, ValueError):
    """Parameters are inconsistent or out of range."""


class WeightsMismatchError(ConfigError):
    """A network weights file does not fit the backbone it was named for (the message names the parameter)."""


# --- processing ------------------------------------------------------------------------
class ProcessingError(GeoCDError, RuntimeError):
    """A method could not produce a result from valid-looking inputs."""


class OutputError(GeoCDError, OSError):
    """An output cannot be written (exists and must not be overwritten, no space, ...)."""


class OutputLockedError(OutputError):
    """Another geocd run is writing into the same output folder."""


class DiskFullError(OutputError):
    """No space left (or a file-size limit reached) where outputs go."""


class ResourceError(GeoCDError, MemoryError):
    """A job needs more memory (or disk) than the machine has; the message says how much and what to change."""


class InternalError(GeoCDError, RuntimeError):
    """An unexpected failure inside geocd (a bug): the message asks for a report with ``--debug``."""


class CancelledError(GeoCDError):
    """The user cancelled a long operation (via the progress callback)."""

    exit_code = 130


class SchedulerError(ProcessingError):
    """A tiled run cannot use the scheduler it was given (unreachable, mismatched workers)."""
