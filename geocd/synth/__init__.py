"""Scene simulator: a synthetic town with two epochs, satellite (RPC) and aerial (frame) views, exact truth.

* :mod:`geocd.synth.scene` — the town (terrain, streets, buildings from footprints, trees, cars) and
  its known changes between epochs A and B;
* :mod:`geocd.synth.sensors` — physical pushbroom line scanner at orbital distance, sun position;
* :mod:`geocd.synth.render` (+ ``_kernels``) — numba ray casting, shading, shadows, sensor model;
* :mod:`geocd.synth.truth` — DSMs, DEM, change masks (map and image geometry), footprints, checks;
* :mod:`geocd.synth.generate` — :class:`SynthParams` and :func:`generate` (what ``geocd synth`` runs).

Importing this package registers the ``pushbroom`` camera kind, so the physical cameras stored in a
scene's ``truth/cameras/*.json`` load with :func:`geocd.camera.camera_from_dict` or :func:`load_truth_camera`.
"""

from __future__ import annotations

import json
import os

from .sensors import PushbroomCamera  # noqa: F401  (registers the "pushbroom" camera kind)


def load_truth_camera(path: os.PathLike | str):
    """The physical camera (pushbroom or frame) of a view from a scene's ``truth/cameras/<name>.json``."""
    from ..camera import camera_from_dict

    with open(path, encoding="utf-8") as f:
        return camera_from_dict(json.load(f))
