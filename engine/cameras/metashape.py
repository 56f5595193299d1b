"""Agisoft Metashape (and PhotoScan) cameras.xml, as written by File > Export > Cameras (Agisoft XML).

The projection is Metashape manual 1.5, appendix C "Camera models", frame cameras:
    x = X/Z, y = Y/Z, r² = x² + y²
    x' = x(1 + K1r² + K2r⁴ + K3r⁶ + K4r⁸) + P1(r² + 2x²) + 2P2xy
    y' = y(1 + K1r² + K2r⁴ + K3r⁶ + K4r⁸) + P2(r² + 2y²) + 2P1xy
    u = w/2 + cx + x'(f + B1) + y'B2,   v = h/2 + cy + y'f
"The image coordinate system has origin at the top left image pixel, with the center of the top left pixel
having coordinates (0.5, 0.5)", and camera x right / y down / z forward, as ours. Hence:
- K = [[f + B1, B2, w/2 + cx - 0.5], [0, f, h/2 + cy - 0.5], [0, 0, 1]];
- OpenCV's p1 multiplies (r² + 2y²) in y' and p2 (r² + 2x²) in x', so p1 = P2 and p2 = P1 (swapped);
- K4 has no OpenCV term: k1..k6 (and, if needed, a focal scale) are fitted to the full radial
  polynomial, refused beyond 0.05 px anywhere up to the image corners (engine.cameras.distortion);
- P3, P4 (which scale the tangential terms) have no OpenCV term either and are refused if non-zero.
PhotoScan before 1.5 wrote fx, fy, absolute cx, cy (same pixel origin) and skew instead of f, cx, cy, B1, B2.

Poses: each aligned camera's <transform> is a row-major 4×4 camera→chunk matrix; components (Metashape
1.6+) may add a component→chunk similarity, and the chunk's own <transform> (rotation, translation, scale)
maps chunk to world coordinates (geocentric when the chunk is georeferenced in a geographic system).
Cameras without <transform> were not aligned and are skipped. Only the first chunk is read.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from engine.cameras.camera import MAX_DISTANCE, MAX_PIXELS, Camera, make_camera
from engine.cameras.distortion import RadialFit, fit_radial, opencv_distortion, undistorted_radius
from engine.cameras.rotations import nearest_rotation
from engine.errors import InputError

PIXEL_ORIGIN_SHIFT = 0.5
"""Metashape pixel coordinate of the top-left pixel centre; subtracted from the principal point."""
MAX_SCALE = 1e9
"""Largest chunk or component <scale>, and 1/MAX_SCALE the smallest: it takes Metashape's internal unit (of the
order of the scene's size) to the world's, a ratio far within 1e9 for any survey and unit (km to mm is 1e6);
beyond, the file is corrupt, and its products with positions overflow or collapse every camera onto one point."""


@dataclass(frozen=True)
class Similarity:
    """X' = scale·R·X + t."""

    R: np.ndarray
    t: np.ndarray
    scale: float = 1.0

    def __matmul__(self, other: Similarity) -> Similarity:
        return Similarity(self.R @ other.R, self.scale * self.R @ other.t + self.t, self.scale * other.scale)


IDENTITY = Similarity(np.eye(3), np.zeros(3))


def read_metashape(path: Path) -> dict[str, Camera]:
    """Aligned cameras of the first chunk of a Metashape cameras.xml, in the chunk's world frame."""
    chunk = _first_chunk(path)
    sensors = {element.get("id"): element for element in chunk.iterfind("sensors/sensor")}
    components = {element.get("id"): _similarity(path, element.find("transform"), f"component {element.get('id')}")
                  for element in chunk.iterfind("components/component")}
    to_world = _similarity(path, chunk.find("transform"), "chunk transform")
    intrinsics: dict[str, tuple[int, int, np.ndarray, np.ndarray]] = {}
    cameras: dict[str, Camera] = {}
    for element in chunk.iterfind("cameras//camera"):
        label = element.get("label") or f"camera {element.get('id')}"
        transform = element.find("transform")
        if transform is None:
            continue  # not aligned
        sensor_id = element.get("sensor_id")
        if sensor_id not in sensors:
            raise InputError(path, f"camera {label!r}: sensor_id {sensor_id!r} is not among the sensors "
                                   f"{sorted(sensors)}")
        if sensor_id not in intrinsics:
            intrinsics[sensor_id] = _sensor(path, sensors[sensor_id])
        if label in cameras:
            raise InputError(path, f"camera label {label!r} appears twice")
        pose = to_world @ components.get(element.get("component_id"), IDENTITY) @ _camera_pose(path, transform, label)
        width, height, K, dist = intrinsics[sensor_id]
        R = pose.R.T  # pose maps camera to world; R maps world to camera
        cameras[label] = make_camera(path, label, width, height, K, dist, R, -R @ pose.t)
    return cameras


def _first_chunk(path: Path) -> ET.Element:
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as error:
        raise InputError(path, f"not well-formed XML: {error}") from None
    except OSError as error:
        raise InputError(path, f"cannot read the file: {error.strerror}") from None
    chunk = root if root.tag == "chunk" else root.find("chunk")
    if root.tag not in ("document", "chunk") or chunk is None:
        raise InputError(path, f"expected a Metashape cameras XML (<document><chunk>…), found <{root.tag}>")
    return chunk


def _sensor(path: Path, sensor: ET.Element) -> tuple[int, int, np.ndarray, np.ndarray]:
    """(width, height, K, OpenCV distortion) of a frame sensor's adjusted (else initial) calibration."""
    where = f"sensor {sensor.get('id')}" + (f" ({sensor.get('label')})" if sensor.get("label") else "")
    if sensor.get("type", "frame") != "frame":
        raise InputError(path, f"{where}: sensor type {sensor.get('type')!r} is not supported; expected "
                               "'frame' (pinhole); fisheye and spherical cameras need undistorted exports")
    calibrations = {c.get("class"): c for c in sensor.iterfind("calibration")}
    calibration = next((calibrations[c] for c in ("adjusted", "initial", None) if c in calibrations), None)
    if calibration is None:
        raise InputError(path, f"{where}: no <calibration>; expected the sensor's adjusted calibration")
    resolution = calibration.find("resolution")
    width, height = _resolution(path, sensor.find("resolution") if resolution is None else resolution, where)
    value = _values(path, calibration, where)
    if value("p3") or value("p4"):
        raise InputError(path, f"{where}: P3/P4 tangential scaling is not supported (OpenCV has no such "
                               "terms); recalibrate without them")
    if calibration.find("fx") is not None:  # PhotoScan < 1.5: absolute principal point, skew
        fx, fy, cx, cy, skew = value("fx"), value("fy"), value("cx"), value("cy"), value("skew")
    else:
        f, b1 = value("f"), value("b1")
        fx, fy, cx, cy, skew = f + b1, f, width / 2 + value("cx"), height / 2 + value("cy"), value("b2")
    K = np.array([[fx, skew, cx - PIXEL_ORIGIN_SHIFT], [0.0, fy, cy - PIXEL_ORIGIN_SHIFT], [0.0, 0.0, 1.0]])
    if not (fx > 0 and fy > 0 and np.abs(K).max() <= MAX_PIXELS):  # checked before the K4 fit divides by them
        raise InputError(path, f"{where}: K = {K.tolist()} (from <f>, <cx>, <cy>, <b1>, <b2>, or <fx>, <fy>, "
                               f"<skew>), expected positive focal lengths and values within {MAX_PIXELS:g} px")
    k1, k2, k3, k4 = (value(n) for n in ("k1", "k2", "k3", "k4"))
    fit = RadialFit(np.array([k1, k2, k3, 0.0, 0.0, 0.0]), 1.0, 0.0)
    if k4:
        fit = _fit_k4(path, where, (k1, k2, k3, k4), K, width, height)
        K[:2, :2] *= fit.scale
    return width, height, K, opencv_distortion(fit.k, p1=value("p2") / fit.scale, p2=value("p1") / fit.scale)


def _fit_k4(path: Path, where: str, k: tuple[float, ...], K: np.ndarray, width: int, height: int) -> RadialFit:
    """OpenCV radial coefficients for Metashape's radial polynomial with an r⁸ term."""
    def model(s: np.ndarray) -> np.ndarray:
        return 1 + s * (k[0] + s * (k[1] + s * (k[2] + s * k[3])))
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [-0.5, height - 0.5], [width - 0.5, height - 0.5]])
    focal = min(K[0, 0], K[1, 1])
    rho = float(np.max(np.hypot(corners[:, 0] - K[0, 2], corners[:, 1] - K[1, 2]))) / focal
    what = f"{where} (K1..K4 = {', '.join(f'{c:g}' for c in k)})"
    return fit_radial(model, undistorted_radius(model, rho, path, what), focal, path, what)


def _camera_pose(path: Path, transform: ET.Element, label: str) -> Similarity:
    m = _numbers(path, transform, 16, f"camera {label!r} <transform>").reshape(4, 4)
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9):
        raise InputError(path, f"camera {label!r} <transform>: last row is {m[3].tolist()}, expected 0 0 0 1")
    R = nearest_rotation(m[:3, :3], path, f"camera {label!r} <transform>")
    return Similarity(R, _position(path, m[:3, 3], f"camera {label!r} <transform> translation"))


def _similarity(path: Path, transform: ET.Element | None, where: str) -> Similarity:
    """A chunk or component <transform> of <rotation>, <translation>, <scale>; identity if absent."""
    if transform is None:
        return IDENTITY
    parts = {tag: transform.find(tag) for tag in ("rotation", "translation", "scale")}
    R = np.eye(3) if parts["rotation"] is None else nearest_rotation(
        _numbers(path, parts["rotation"], 9, f"{where} <rotation>").reshape(3, 3), path, f"{where} <rotation>")
    t = np.zeros(3) if parts["translation"] is None else _position(
        path, _numbers(path, parts["translation"], 3, f"{where} <translation>"), f"{where} <translation>")
    scale = 1.0 if parts["scale"] is None else float(_numbers(path, parts["scale"], 1, f"{where} <scale>")[0])
    if not 1 / MAX_SCALE <= scale <= MAX_SCALE:
        raise InputError(path, f"{where} <scale>: {scale:g}, expected a number from {1 / MAX_SCALE:g} to "
                               f"{MAX_SCALE:g}")
    return Similarity(R, t, scale)


def _position(path: Path, t: np.ndarray, where: str) -> np.ndarray:
    """A translation, refused beyond MAX_DISTANCE (no place on Earth), where its products would overflow."""
    if np.abs(t).max() > MAX_DISTANCE:
        raise InputError(path, f"{where}: {t.tolist()}, expected coordinates within ±{MAX_DISTANCE:g}")
    return t


def _resolution(path: Path, element: ET.Element | None, where: str) -> tuple[int, int]:
    try:
        width, height = int(element.get("width")), int(element.get("height"))
    except (AttributeError, TypeError, ValueError):
        raise InputError(path, f"{where}: expected <resolution width=\"…\" height=\"…\"/> with integers") from None
    return width, height


def _values(path: Path, calibration: ET.Element, where: str):
    """Reader of one calibration value by tag; absent tags are 0."""
    def value(tag: str) -> float:
        element = calibration.find(tag)
        return 0.0 if element is None else float(_numbers(path, element, 1, f"{where} <{tag}>")[0])
    return value


def _numbers(path: Path, element: ET.Element, count: int, where: str) -> np.ndarray:
    tokens = (element.text or "").split()
    if len(tokens) != count:
        raise InputError(path, f"{where}: expected {count} numbers, found {len(tokens)}")
    try:
        values = np.array([float(token) for token in tokens])
    except ValueError:
        raise InputError(path, f"{where}: expected {count} numbers, found {element.text.strip()!r}") from None
    if not np.all(np.isfinite(values)):
        raise InputError(path, f"{where}: expected finite numbers, found {element.text.strip()!r}")
    return values
