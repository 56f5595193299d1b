"""VisualSFM NVM_V3 files.

Format (VisualSFM documentation, "NVM file format"): a header line NVM_V3, then models, each
    <number of cameras>, one line per camera: <file name> <f> <qw qx qy qz> <Cx Cy Cz> <r> 0
    <number of points>, one line per point: <X Y Z> <R G B> <n> (<image index> <feature index> <x y>)×n
ending with a model of 0 cameras. Conventions converted here:
- the quaternion rotates world to camera (x right, y down, z forward) and C is the camera centre: t = -R·C;
- measurements are relative to the image centre (principal point at the centre, y down); with the
  pixel-corner centre (w/2, h/2) of SiftGPU's coordinates that is our (w/2 - 0.5, h/2 - 0.5);
- r is a radial distortion of the *measured* point: x_undistorted = x·(1 + r·‖x/f‖²), i.e. an
  undistortion, the inverse of OpenCV's model. It is converted by fitting OpenCV's k1..k6 to the inverse
  on the radii the image spans (engine.cameras.distortion; refused if off by more than 0.05 px).
Only the first model is read (VisualSFM writes the largest first). The FixedK header variant
("NVM_V3 FixedK fx cx fy cy r") is refused: writers disagree on whether its cx, cy are absolute or offsets.
The file stores no image sizes: they come from the photos' headers (names are relative to the .nvm file's
folder) unless given as `image_sizes`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from engine.cameras.camera import Camera, make_camera
from engine.cameras.distortion import MAX_RADIAL_FACTOR, RadialFit, fit_radial, opencv_distortion
from engine.cameras.images import ImageSizes, sizes_for
from engine.cameras.rotations import quaternion_to_matrix
from engine.cameras.text import TextLines, parse_numbers
from engine.errors import InputError

HEADER = "NVM_V3"


def read_nvm(path: Path, *, image_sizes: ImageSizes | None = None,
             image_dir: Path | None = None) -> dict[str, Camera]:
    """Cameras of the first model of an NVM_V3 file."""
    lines = TextLines(path)
    number, header = lines.next(f"the header {HEADER!r}")
    if header.split() != [HEADER]:
        found = " ".join(header.split()[:2])
        raise InputError(path, f"line {number}: expected the header {HEADER!r} alone, found {found!r}"
                               + (" (fixed calibration is not supported)" if "FixedK" in header else ""))
    n_cameras = lines.integer("the number of cameras")
    entries = [_camera_line(path, *lines.next(f"camera {i + 1} of {n_cameras}")) for i in range(n_cameras)]
    names = [Path(stored).name for stored, _ in entries]
    if len(set(names)) != len(names):
        raise InputError(path, "two cameras have the same file name; expected unique names")
    sizes = sizes_for([stored for stored, _ in entries], path, image_sizes, image_dir or path.parent)
    return {name: _to_camera(path, name, sizes[stored], values, str(path.parent / stored))
            for name, (stored, values) in zip(names, entries)}


def _camera_line(path: Path, number: int, text: str) -> tuple[str, np.ndarray]:
    """(file name, [f qw qx qy qz Cx Cy Cz r 0]); the name may hold spaces, so split from the right."""
    tokens = text.rsplit(maxsplit=10)
    if len(tokens) != 11:
        raise InputError(path, f"line {number}: expected <name> <f> <qw qx qy qz> <Cx Cy Cz> <r> 0, "
                               f"found {len(tokens)} values")
    values = parse_numbers(path, number, tokens[1:], "f qw qx qy qz Cx Cy Cz r 0", 10)
    if values[0] <= 0:
        raise InputError(path, f"line {number}: focal length {values[0]}, expected > 0")
    return tokens[0].replace("\\", "/"), values


def _to_camera(path: Path, name: str, size: tuple[int, int], values: np.ndarray, image_path: str) -> Camera:
    f, q, C, r = values[0], values[1:5], values[5:8], values[8]
    width, height = size
    R = quaternion_to_matrix(q, path, f"camera {name!r}")
    fit = _inverse_radial(path, name, r, width, height, f) if r else RadialFit(np.zeros(6), 1.0, 0.0)
    K = np.array([[f * fit.scale, 0.0, width / 2 - 0.5], [0.0, f * fit.scale, height / 2 - 0.5], [0.0, 0.0, 1.0]])
    return make_camera(path, name, width, height, K, opencv_distortion(fit.k), R, -R @ C, image_path)


def _inverse_radial(path: Path, name: str, r: float, width: int, height: int, f: float) -> RadialFit:
    """OpenCV radial coefficients for the inverse of VisualSFM's x_u = x_d·(1 + r·‖x_d‖²)."""
    rho_d = np.hypot(width / 2, height / 2) / f  # a corner, distorted (measured), normalised
    # The corner moves to ρ(1 + rρ²): the model folds before it unless rρ² > -1/3, and 1 + rρ² may not exceed
    # MAX_RADIAL_FACTOR (a larger r is no lens, and its powers would overflow the fit).
    low, high = -1 / (3 * rho_d**2), (MAX_RADIAL_FACTOR - 1) / rho_d**2
    if not low < r <= high:
        raise InputError(path, f"camera {name!r}: radial distortion r = {r:g} is out of range for this "
                               f"{width}×{height} photo at f = {f:g} px: expected {low:.4g} < r <= {high:.4g} (a "
                               f"smaller r folds the image before its corners, a larger one undistorts them to "
                               f"more than {MAX_RADIAL_FACTOR:g} times their distance from the centre)")

    def model(s: np.ndarray) -> np.ndarray:
        rho_u = np.sqrt(s)
        rho = rho_u.copy()
        for _ in range(30):  # Newton on r·ρ³ + ρ - ρ_u = 0, monotonic on the branch checked above
            rho -= (r * rho**3 + rho - rho_u) / (3 * r * rho**2 + 1)
        return np.divide(rho, rho_u, out=np.ones_like(rho), where=rho_u > 0)

    return fit_radial(model, rho_d * (1 + r * rho_d**2), f, path, f"camera {name!r} radial distortion r = {r:g}")
