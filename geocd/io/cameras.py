"""Find and load the camera model of an image, whatever its kind.

Order: an explicit camera file (from the manifest or the command line), then
RPC tags in the image, then an RPC sidecar, then a frame-camera sidecar. The
result is a :class:`geocd.camera.Camera` with the image size set.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..camera import Camera, camera_from_dict
from ..errors import CameraError, GeoCDError, InputFileNotFoundError, NoCameraError, RPCNotFoundError, RPCParseError
from .safe_yaml import YAMLLimitError, load_json, load_yaml


def _image_size(image: Path) -> tuple[int | None, int | None]:
    from ..errors import GeoCDError
    from .raster import _open

    try:
        with _open(image) as ds:
            return ds.width, ds.height
    except GeoCDError:
        return None, None


def _with_size(cam: Camera, width: int | None, height: int | None) -> Camera:
    if width is None or (cam.width == width and cam.height == height):
        return cam
    if cam.width is not None and hasattr(cam, "rescaled"):
        # the image was resampled after the camera was calibrated (e.g. a downsampled aerial frame):
        # scale the interior orientation, never just relabel the size
        import warnings

        warnings.warn(
            f"camera was calibrated for {cam.width}x{cam.height} px but the image is {width}x{height} px; "
            "rescaling its interior orientation to the image",
            stacklevel=3,
        )
        return cam.rescaled(width, height)
    d = cam.to_dict()
    d["width"], d["height"] = width, height
    return camera_from_dict(d)


def read_camera_file(path: os.PathLike | str, image_path: os.PathLike | str | None = None) -> Camera:
    """Read a camera file: geocd JSON/YAML (any kind) or any vendor RPC format.

    Every camera read goes through the plausibility checks of its kind (:func:`check_camera_plausible`),
    whatever the file's format.

    Raises
    ------
    InputFileNotFoundError, RPCParseError, FrameCameraError, CameraError
    """
    p = Path(path)
    if not p.exists():
        raise InputFileNotFoundError(f"camera file {p} does not exist; check the path in the manifest")
    if p.suffix.lower() in (".json", ".yaml", ".yml"):
        text = p.read_text(encoding="utf-8", errors="replace")
        try:
            d = load_json(text) if p.suffix.lower() == ".json" else load_yaml(text)
        except YAMLLimitError as exc:
            raise RPCParseError(f"camera file {p}: {exc}") from None
        except Exception:
            d = None  # not JSON/YAML: the RPC reader below names what is wrong
        if isinstance(d, dict) and d.get("kind") == "frame":
            from .frame import read_frame_sidecar

            return read_frame_sidecar(p)
        if isinstance(d, dict) and "kind" in d:
            try:
                cam = camera_from_dict(d)
            except (TypeError, ValueError, KeyError, OverflowError) as exc:
                if isinstance(exc, GeoCDError):
                    raise type(exc)(f"camera file {p}: {exc}") from None
                raise CameraError(
                    f"camera file {p}: invalid camera description ({type(exc).__name__}: "
                    f"{str(exc)[:160]}); re-export it with geocd"
                ) from None
            return check_camera_plausible(cam, p)
    from .rpc import read_rpc

    return read_rpc(p, image_path=image_path)


def check_camera_plausible(cam: Camera, path: os.PathLike | str | None = None) -> Camera:
    """The checks of a camera's kind, for a camera built from a description (``camera_from_dict``): an RPC's
    offsets, scales and coefficients (:func:`geocd.io.rpc.check_rpc_plausible`), the base camera of a
    corrected one. Frame cameras check themselves when they are built.

    Raises
    ------
    RPCParseError
    """
    from ..camera import CorrectedCamera, RPCModel
    from .rpc import check_rpc_plausible

    if isinstance(cam, RPCModel):
        check_rpc_plausible(cam, path)
    elif isinstance(cam, CorrectedCamera):
        check_camera_plausible(cam.base, path)
    return cam


def load_camera(image_path: os.PathLike | str, camera_path: os.PathLike | str | None = None) -> Camera:
    """The camera model of an image.

    Parameters
    ----------
    image_path : the image file
    camera_path : optional explicit camera file (RPC in any vendor format, or a geocd
        frame/RPC JSON/YAML sidecar)

    Raises
    ------
    NoCameraError
        When the image has no RPC tags, no RPC sidecar and no frame sidecar.
    """
    image = Path(image_path)
    if not image.exists():
        raise InputFileNotFoundError(f"image {image} does not exist; check the path")
    width, height = _image_size(image)
    if camera_path is not None:
        return _with_size(read_camera_file(camera_path, image_path=image), width, height)
    from .rpc import load_rpc_for_image

    try:
        return load_rpc_for_image(image)
    except RPCNotFoundError:
        pass
    from .frame import find_frame_sidecar, read_frame_sidecar

    side = find_frame_sidecar(image)
    if side is not None:
        return _with_size(read_frame_sidecar(side), width, height)
    raise NoCameraError(
        f"{image} has no camera model: no RPC tags, no RPC sidecar (_rpc.txt, .RPB, RPC_*.XML, .geom, ...) and no "
        f"frame-camera sidecar ({image.stem}.camera.json/.yaml); put the camera file next to the image or name it "
        "with 'camera:' in the manifest"
    )
