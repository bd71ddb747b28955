"""Variable-resolution probabilistic volume model and image-based change detection.

After Crispell, Mundy and Taubin, "A Variable-Resolution Probabilistic
Three-Dimensional Model for Change Detection" (IEEE TGRS 2012; VXL boxm2 is the
reference implementation): the scene is an occlusion-density field α (1/m) plus
per-cell appearance mixtures, stored in a grid of shallow octrees in a local ENU
frame, learned online from images with known cameras (any kind of the camera
protocol), and used to predict how probable each pixel of a new image is.

Typical use::

    from geocd.volume import (VolumeModel, geometry_for_aoi, update_model, detect_change,
                              image_intensity, save_model, load_model, seed_from_dem)
    geom = geometry_for_aoi(aoi_grid, z_min_m=dem_min - 3, z_max_m=dem_max + 30, finest_cell_m=0.5)
    model = VolumeModel.create(geom, init_depth=1)
    seed_from_dem(model, dem_height_m, aoi_grid)    # optional DEM prior (geocd extension)
    for img, cam, sun in training_images:          # several passes help refinement
        update_model(model, image_intensity(img.data, img.valid, img.bit_depth), cam, sun=sun)
    result = detect_change(model, new_intensity, new_camera, sun=new_sun)   # relit when the sun is new
    save_model(model, "out/volume_model")

See ``docs/volume.md`` for the method notes and results.
"""

from .detect import ChangeResult, DetectParams, change_probability, detect_change
from .io import disk_bytes, load_model, read_view, save_model
from .prior import DEMPrior, seed_from_dem
from .rays import check_camera_sees_volume, pixel_rays
from .refine import cells_to_split, coarsen_model, refine_model
from .render import RenderResult, expected_height_map, expected_image, orthorectify, render_image
from .scene import VolumeGeometry, VolumeModel, VolumeParams, geometry_for_aoi
from .update import UpdateStats, image_intensity, update_model

__all__ = [
    "VolumeGeometry",
    "VolumeModel",
    "VolumeParams",
    "geometry_for_aoi",
    "pixel_rays",
    "check_camera_sees_volume",
    "update_model",
    "image_intensity",
    "UpdateStats",
    "refine_model",
    "cells_to_split",
    "coarsen_model",
    "seed_from_dem",
    "DEMPrior",
    "detect_change",
    "DetectParams",
    "ChangeResult",
    "change_probability",
    "render_image",
    "expected_image",
    "expected_height_map",
    "orthorectify",
    "RenderResult",
    "save_model",
    "load_model",
    "disk_bytes",
    "read_view",
]
