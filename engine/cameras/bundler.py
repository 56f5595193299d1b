"""Bundler v0.3 bundle files (bundle.out) with their image list.

Format and projection, Bundler user manual (snavely/bundler_sfm README, "Output format"):
    P = R·X + t,  p = -P/P.z,  p' = f·r(p)·p,  r(p) = 1 + k1‖p‖² + k2‖p‖⁴
"the origin of the image is the center of the image, the positive x-axis points right, and the positive
y-axis points up … the camera is looking down the negative z-axis"; (-w/2, -h/2) is the lower-left corner
of the image, so the image centre is the pixel-corner point (w/2, h/2). Conversion to ours:
- camera frame: OpenCV = diag(1, -1, -1)·Bundler, so R_cv = D·R, t_cv = D·t; then x_cv/z_cv = p.x and
  y_cv/z_cv = -p.y, i.e. the same normalised point with y flipped;
- k1, k2 act on p in normalised units (p is divided by P.z before f is applied): they are OpenCV's k1, k2
  exactly, with no factor of f;
- principal point: the image centre, (w/2 - 0.5, h/2 - 0.5) with our top-left pixel centre at (0, 0);
  a Bundler key point (x, y) is our pixel (x + w/2 - 0.5, h/2 - 0.5 - y).
Cameras with f = 0 were not reconstructed and are skipped.

Names come from the image list Bundler was given (list.txt: "path [0 focal]" per line, in camera order),
found beside the .out file as <name>.list.txt, <stem>.list.txt or list.txt, or one folder up (Bundler's
own layout puts bundle.out in bundle/). Without a list the cameras are named image000, image001, ….
The .out file stores no image sizes: they are read from the photos' headers (found under `image_dir`,
default the list's folder) unless given as `image_sizes`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from engine.cameras.camera import Camera, make_camera
from engine.cameras.images import ImageSizes, sizes_for
from engine.cameras.rotations import nearest_rotation
from engine.cameras.text import TextLines, read_text
from engine.errors import InputError

HEADER = "# Bundle file v0.3"
FLIP = np.diag([1.0, -1.0, -1.0])
"""Bundler camera (x right, y up, z backward) to OpenCV camera (x right, y down, z forward)."""


def read_bundler(path: Path, *, image_list: Path | None = None, image_sizes: ImageSizes | None = None,
                 image_dir: Path | None = None) -> dict[str, Camera]:
    """Reconstructed cameras of a Bundler v0.3 file, named from its image list."""
    lines = TextLines(path, comment=None)
    _, header = lines.next(f"the header {HEADER!r}")
    if header != HEADER:
        raise InputError(path, f"line 1: expected the header {HEADER!r}, found {header[:40]!r}")
    n_cameras, _ = lines.counts("<num_cameras> <num_points>", 2)
    # Cameras are read before names are made, so a corrupt count ends at the end of the file, not in memory.
    read = [_camera(lines, path, index) for index in range(n_cameras)]
    list_path = image_list if image_list is not None else find_image_list(path)
    paths = _image_paths(path, list_path, n_cameras)
    names = [Path(p).name for p in paths]
    poses = {name: pose for name, pose in zip(names, read) if pose[0] > 0}
    folder = list_path.parent if list_path else path.parent  # list entries are relative to it
    stored = dict(zip(names, paths))
    sizes = sizes_for([stored[name] for name in poses], path, image_sizes, image_dir or folder)
    return {name: _to_camera(path, name, sizes[stored[name]], *pose,
                             str(folder / stored[name]) if list_path else None)
            for name, pose in poses.items()}


def find_image_list(path: Path) -> Path | None:
    """The image list beside a bundle file, or one folder up (Bundler's layout)."""
    candidates = [path.with_name(path.name + ".list.txt"), path.with_name(path.stem + ".list.txt"),
                  path.with_name("list.txt"), path.parent.parent / "list.txt"]
    return next((c for c in candidates if c.is_file()), None)


def _image_paths(path: Path, list_path: Path | None, n_cameras: int) -> list[str]:
    """The image of each camera as the list gives it, or image000, image001, … without a list."""
    if list_path is None:
        return [f"image{i:03d}" for i in range(n_cameras)]
    if not list_path.is_file():
        raise InputError(list_path, f"image list of {path.name} not found; expected one image path per camera")
    entries = [line.split()[0] for line in read_text(list_path).splitlines() if line.strip()]
    if len(entries) != n_cameras:
        raise InputError(list_path, f"the image list has {len(entries)} entries but the bundle file has "
                                    f"{n_cameras} cameras; expected one line per camera, in order")
    paths = [entry.replace("\\", "/").removeprefix("./") for entry in entries]
    if len({Path(p).name for p in paths}) != len(paths):
        raise InputError(list_path, "two images in the list have the same file name; expected unique names")
    return paths


def _camera(lines: TextLines, path: Path, index: int) -> tuple[float, float, float, np.ndarray, np.ndarray]:
    """(f, k1, k2, R, t) of camera `index` as stored (Bundler frame)."""
    f, k1, k2 = lines.numbers(f"camera {index}: <f> <k1> <k2>", 3)
    R = np.array([lines.numbers(f"camera {index}: rotation row {row}", 3) for row in range(3)])
    t = lines.numbers(f"camera {index}: translation <t>", 3)
    if f < 0:
        raise InputError(path, f"camera {index}: focal length {f}, expected >= 0")
    if f > 0:
        R = nearest_rotation(R, path, f"camera {index} rotation")
    return f, k1, k2, R, t


def _to_camera(path: Path, name: str, size: tuple[int, int], f: float, k1: float, k2: float, R: np.ndarray,
               t: np.ndarray, image_path: str) -> Camera:
    width, height = size
    K = np.array([[f, 0.0, width / 2 - 0.5], [0.0, f, height / 2 - 0.5], [0.0, 0.0, 1.0]])
    return make_camera(path, name, width, height, K, [k1, k2], FLIP @ R, FLIP @ t, image_path)
