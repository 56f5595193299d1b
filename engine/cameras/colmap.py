"""COLMAP sparse models: cameras.txt/images.txt and cameras.bin/images.bin.

Format: https://colmap.github.io/format.html (text) and colmap/src/colmap/scene/reconstruction_io.cc
(binary, little-endian). Conventions converted here (DESIGN.md):
- pose QW QX QY QZ TX TY TZ is world→camera, camera x right / y down / z forward: R, t taken as they are;
- COLMAP puts the centre of the top-left pixel at (0.5, 0.5) (format.html, "the upper left pixel centre is
  (0.5, 0.5)"); ours is (0, 0), so cx, cy lose 0.5;
- distortion of SIMPLE_RADIAL/RADIAL/OPENCV/FULL_OPENCV is OpenCV's, in normalised coordinates.
"""

from __future__ import annotations

from collections.abc import Container
from pathlib import Path

import numpy as np

from engine.cameras.binary import BinaryReader
from engine.cameras.camera import Camera, make_camera
from engine.cameras.rotations import quaternion_to_matrix
from engine.cameras.text import TextLines, parse_count, parse_numbers
from engine.errors import InputError

PIXEL_ORIGIN_SHIFT = 0.5
"""COLMAP pixel coordinate of the top-left pixel centre; subtracted from cx, cy."""

# name: (model id in .bin files, number of parameters); ids from colmap/src/colmap/sensor/models.h
MODELS = {"SIMPLE_PINHOLE": (0, 3), "PINHOLE": (1, 4), "SIMPLE_RADIAL": (2, 4), "RADIAL": (3, 5),
          "OPENCV": (4, 8), "FULL_OPENCV": (6, 12)}
_UNSUPPORTED = {5: "OPENCV_FISHEYE", 7: "FOV", 8: "SIMPLE_RADIAL_FISHEYE", 9: "RADIAL_FISHEYE",
                10: "THIN_PRISM_FISHEYE"}
_NAME_OF_ID = {model_id: name for name, (model_id, _) in MODELS.items()}

Intrinsics = tuple[int, int, np.ndarray, np.ndarray]
"""(width, height, K, distortion) of one COLMAP camera."""


def model_files(path: Path) -> tuple[Path, Path] | None:
    """(cameras, images) files of the COLMAP model at `path` (a folder or one of its files), if any."""
    folder = path if path.is_dir() else path.parent
    for suffix in (".bin", ".txt"):  # COLMAP's own readers prefer the binary model
        cameras, images = folder / f"cameras{suffix}", folder / f"images{suffix}"
        if path.is_dir() or path.suffix == suffix:
            if cameras.is_file() and images.is_file():
                return cameras, images
    return None


def read_colmap(path: Path) -> dict[str, Camera]:
    """Cameras of a COLMAP model; `path` is its folder, or its cameras or images file."""
    files = model_files(path)
    if files is None:
        raise InputError(path, "expected a COLMAP model: cameras.txt and images.txt (or cameras.bin and "
                               "images.bin) in one folder")
    cameras_file, images_file = files
    if cameras_file.suffix == ".bin":
        return _images_bin(images_file, _cameras_bin(cameras_file))
    return _images_txt(images_file, _cameras_txt(cameras_file))


def intrinsics(model: str, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """K (in our pixel convention) and OpenCV distortion from COLMAP model parameters."""
    p = list(params)
    if model == "SIMPLE_PINHOLE":
        (f, cx, cy), dist = p, []
        fx = fy = f
    elif model in ("SIMPLE_RADIAL", "RADIAL"):
        (f, cx, cy), dist = p[:3], p[3:]
        fx = fy = f
    else:  # PINHOLE, OPENCV, FULL_OPENCV: fx, fy, cx, cy, then OpenCV's k1, k2, p1, p2, k3, k4, k5, k6
        (fx, fy, cx, cy), dist = p[:4], p[4:]
    K = np.array([[fx, 0.0, cx - PIXEL_ORIGIN_SHIFT], [0.0, fy, cy - PIXEL_ORIGIN_SHIFT], [0.0, 0.0, 1.0]])
    return K, np.array(dist, dtype=float)


def _cameras_txt(path: Path) -> dict[int, Intrinsics]:
    lines, cameras = TextLines(path), {}
    while not lines.at_end():
        number, text = lines.next("a camera line: CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        tokens = text.split()
        if len(tokens) < 4:
            raise InputError(path, f"line {number}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], "
                                   f"found {len(tokens)} values")
        camera_id = parse_count(path, number, tokens[0], "CAMERA_ID")
        model = _check_model(path, f"line {number}", tokens[1])
        width, height = (parse_count(path, number, t, what) for t, what in zip(tokens[2:4], ("WIDTH", "HEIGHT")))
        params = parse_numbers(path, number, tokens[4:], f"the {model} parameters", MODELS[model][1])
        _check_unique(path, f"line {number}", "CAMERA_ID", camera_id, cameras)
        cameras[camera_id] = (width, height, *intrinsics(model, params))
    return cameras


def _images_txt(path: Path, cameras: dict[int, Intrinsics]) -> dict[str, Camera]:
    # Each image is a header line then a POINTS2D line that may be empty, so blank lines are kept.
    lines, result, ids = TextLines(path, skip_blank=False), {}, set()
    while not lines.at_end():
        number, text = lines.next("an image line")
        if not text:
            continue
        tokens = text.split(maxsplit=9)
        if len(tokens) != 10:
            raise InputError(path, f"line {number}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, "
                                   f"found {len(tokens)} values")
        image_id = parse_count(path, number, tokens[0], "IMAGE_ID")
        values = parse_numbers(path, number, tokens[1:8], "QW QX QY QZ TX TY TZ", 7)
        camera_id = parse_count(path, number, tokens[8], "CAMERA_ID")
        _check_unique(path, f"line {number}", "IMAGE_ID", image_id, ids)
        ids.add(image_id)
        _add(result, path, f"line {number}", tokens[9], values, camera_id, cameras)
        if not lines.at_end():
            lines.next("the POINTS2D line")
    return result


def _cameras_bin(path: Path) -> dict[int, Intrinsics]:
    reader, cameras = BinaryReader(path), {}
    for _ in range(reader.count("Q", 24, "cameras")):
        where = f"byte {reader.offset}"
        camera_id, model_id, width, height = reader.unpack("iiQQ", "CAMERA_ID MODEL_ID WIDTH HEIGHT")
        model = _check_model(path, where, _NAME_OF_ID.get(model_id, _UNSUPPORTED.get(model_id, str(model_id))))
        n = MODELS[model][1]
        params = reader.doubles(n, f"{n} {model} parameters")
        _check_unique(path, where, "CAMERA_ID", camera_id, cameras)
        cameras[camera_id] = (width, height, *intrinsics(model, params))
    return cameras


def _images_bin(path: Path, cameras: dict[int, Intrinsics]) -> dict[str, Camera]:
    reader, result, ids = BinaryReader(path), {}, set()
    for _ in range(reader.count("Q", 64, "images")):
        where = f"byte {reader.offset}"
        (image_id,) = reader.unpack("i", "IMAGE_ID")
        values = reader.doubles(7, "QW QX QY QZ TX TY TZ")
        (camera_id,) = reader.unpack("i", "CAMERA_ID")
        name = reader.cstring("the image NAME")
        n_points = reader.count("Q", 24, "2D points")
        reader.skip(24 * n_points, "the 2D points (x, y, point3D_id)")
        _check_unique(path, where, "IMAGE_ID", image_id, ids)
        ids.add(image_id)
        _add(result, path, where, name, values, camera_id, cameras)
    return result


def _add(result: dict[str, Camera], path: Path, where: str, name: str, pose: np.ndarray, camera_id: int,
         cameras: dict[int, Intrinsics]) -> None:
    if camera_id not in cameras:
        raise InputError(path, f"{where}: image {name!r} uses CAMERA_ID {camera_id}, which the cameras file "
                               f"does not define (defined: {sorted(cameras)})")
    if name in result:
        raise InputError(path, f"{where}: image name {name!r} appears twice")
    width, height, K, dist = cameras[camera_id]
    R = quaternion_to_matrix(pose[:4], path, f"{where}, image {name!r}")
    result[name] = make_camera(path, name, width, height, K, dist, R, pose[4:7])


def _check_unique(path: Path, where: str, what: str, value: int, seen: Container[int]) -> None:
    """Refuse an id given twice: one entry would silently replace the other."""
    if value in seen:
        raise InputError(path, f"{where}: {what} {value} appears twice; expected unique ids")


def _check_model(path: Path, where: str, model: str) -> str:
    if model not in MODELS:
        raise InputError(path, f"{where}: camera model {model!r} is not supported; expected one of "
                               f"{', '.join(MODELS)} (undistort fisheye photos with COLMAP first)")
    return model
