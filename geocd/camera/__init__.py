"""Camera models behind one protocol (:class:`~geocd.camera.base.Camera`).

* :class:`~geocd.camera.rpc.RPCModel` — rational polynomial (satellite) cameras.
* :class:`~geocd.camera.frame.FrameCamera` — pinhole (aerial frame) cameras.

Later code uses only the protocol (project, localize, dproj_dh, ground_projector);
it never asks which kind it holds.
"""

from .base import Camera, GroundProjector, camera_from_dict, register_camera  # noqa: F401
from .rpc import RPCModel  # noqa: F401
from .frame import FrameCamera  # noqa: F401
from .corrected import CorrectedCamera  # noqa: F401
