"""Calibrated cameras and the readers of the photogrammetry formats users bring.

`read_cameras` detects the format from the content and converts every camera to our convention
(DESIGN.md: OpenCV model, x_cam = R·X + t, pixel (0, 0) at the centre of the top-left pixel). Each format's
conventions, and the sources they were checked against, are documented in its reader module.
"""

from __future__ import annotations

from pathlib import Path

from engine.cameras.bundler import read_bundler
from engine.cameras.camera import Camera, check_cameras_see, check_invertible
from engine.cameras.colmap import read_colmap
from engine.cameras.detect import FORMATS, detect_format
from engine.cameras.images import ImageSizes, check_images, image_size
from engine.cameras.metashape import read_metashape
from engine.cameras.native import read_native, write_cameras_json
from engine.cameras.nvm import read_nvm
from engine.cameras.openmvg import read_openmvg
from engine.cameras.openmvs import read_openmvs
from engine.errors import InputError

__all__ = ["FORMATS", "Camera", "ImageSizes", "check_cameras_see", "check_images", "detect_format", "image_size", "read_cameras",
           "write_cameras_json"]


def read_cameras(path: str | Path, *, image_dir: str | Path | None = None,
                 image_sizes: ImageSizes | None = None, image_list: str | Path | None = None) -> dict[str, Camera]:
    """All calibrated cameras in `path`, by image name, in our convention.

    Parameters
    ----------
    path : a COLMAP model folder (or its cameras/images file), Metashape cameras.xml, Bundler .out,
        VisualSFM .nvm, OpenMVG sfm_data.json, OpenMVS .mvs or tracemap cameras JSON.
    image_dir : where the photos are, for formats that store no image size (Bundler, NVM, OpenMVS with
        normalised intrinsics): their sizes are read from the photo headers. Default: beside the file.
    image_sizes : (width, height) of every photo, or a mapping name → (width, height), for those formats
        when the photos are not at hand. Ignored by formats that store sizes.
    image_list : Bundler only: the list of images the bundle was computed from (default: found beside it).

    Cameras that the tool did not calibrate (not aligned, no pose) are left out; a file with none at all
    is an error, and so is a camera whose lens distortion does not invert over its image (`check_invertible`).
    """
    path = Path(path)
    image_dir = None if image_dir is None else Path(image_dir)
    kind = detect_format(path)
    if kind == "bundler":
        cameras = read_bundler(path, image_list=None if image_list is None else Path(image_list),
                               image_sizes=image_sizes, image_dir=image_dir)
    elif kind in ("nvm", "openmvs"):
        reader = read_nvm if kind == "nvm" else read_openmvs
        cameras = reader(path, image_sizes=image_sizes, image_dir=image_dir)
    else:
        cameras = {"colmap": read_colmap, "metashape": read_metashape, "openmvg": read_openmvg,
                   "tracemap": read_native}[kind](path)
    if not cameras:
        raise InputError(path, f"no calibrated camera in this {kind} file; expected at least one aligned camera")
    for camera in cameras.values():
        check_invertible(camera, path)
    return cameras
