"""OpenMVG sfm_data.json (cereal JSON archive of SfM_Data).

Layout (openMVG src/openMVG/sfm/sfm_data_io_cereal.hpp and cameras/*_io.hpp): "views" and "intrinsics" are
lists of {key, value}; each value is a cereal polymorphic pointer {polymorphic_id, [polymorphic_name],
ptr_wrapper: {id, data}}. cereal writes a type's name and a pointer's data only at their first occurrence;
later ones repeat the id (with the top bit clear), so both are resolved through the earlier ones.
"extrinsics" are {key: pose id, value: {rotation (3 rows), center}}.
Conventions (openMVG cameras/Camera_Pinhole*.hpp):
- x_cam = R·(X - C), camera x right / y down / z forward: t = -R·C;
- pixels: cam2ima(p) = f·p + principal_point, and UndistortImage samples pixel (i, j) at (i, j), so pixel
  (0, 0) is the centre of the top-left pixel, as ours: no shift;
- pinhole_radial_k1/k3: p·(1 + k1r² + k2r⁴ + k3r⁶), OpenCV's radial terms;
- pinhole_brown_t2 "disto_t2" = [k1, k2, k3, t1, t2] with x_d += t2(r² + 2x²) + 2t1·xy and
  y_d += t1(r² + 2y²) + 2t2·xy (Camera_Pinhole_Brown.hpp): t1 = OpenCV p1, t2 = OpenCV p2.
Views without a pose or an intrinsic (not reconstructed) are skipped.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from engine.cameras.camera import Camera, make_camera
from engine.cameras.rotations import nearest_rotation
from engine.cameras.text import is_json_number, load_json
from engine.errors import InputError

_ID_MASK = 0x7FFFFFFF  # cereal marks a first occurrence by setting the top bit of the 32-bit id
_MAX_INDEX = 0xFFFFFFFF
_DISTORTION_KEYS = {"pinhole": None, "pinhole_radial_k1": "disto_k1", "pinhole_radial_k3": "disto_k3",
                    "pinhole_brown_t2": "disto_t2"}


def read_openmvg(path: Path) -> dict[str, Camera]:
    """Reconstructed views of an OpenMVG sfm_data.json."""
    data = load_json(path)
    for key in ("views", "intrinsics", "extrinsics"):
        if not isinstance(data.get(key), list):
            raise InputError(path, f"expected an OpenMVG sfm_data with a {key!r} list (export with "
                                   "openMVG_main_ConvertSfM_DataFormat … ALL)")
    root = Path(_string(path, data, "root_path", "sfm_data", default=""))
    pointers: dict[int, dict] = {}
    intrinsics = _intrinsics(path, data["intrinsics"], pointers)
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for entry in data["extrinsics"]:
        key = _new_key(path, entry, poses, "extrinsic")
        poses[key] = _pose(path, key, entry)
    cameras: dict[str, Camera] = {}
    for entry in data["views"]:
        where = f"view {_index(path, entry, 'key', 'view')}"
        view = _pointer_data(path, _field(path, entry, "value", where), pointers, where)
        name = _string(path, view, "filename", where)
        _index(path, view, "id_view", f"view {name!r}")  # not needed, but a file openMVG cannot load is refused
        intrinsic = intrinsics.get(_index(path, view, "id_intrinsic", f"view {name!r}"))
        pose = poses.get(_index(path, view, "id_pose", f"view {name!r}"))
        if intrinsic is None or pose is None:
            continue  # not reconstructed
        if name in cameras:
            raise InputError(path, f"view filename {name!r} appears twice")
        width, height, K, dist = intrinsic
        R, C = pose
        image_path = str(root / _string(path, view, "local_path", f"view {name!r}", default="") / name)
        cameras[name] = make_camera(path, name, width, height, K, dist, R, -R @ C, image_path)
    return cameras


def _intrinsics(path: Path, entries: list, pointers: dict[int, dict]) -> dict:
    names: dict[int, str] = {}
    result = {}
    for entry in entries:
        key = _new_key(path, entry, result, "intrinsic")
        value = _field(path, entry, "value", f"intrinsic {key}")
        type_id = _index(path, value, "polymorphic_id", f"intrinsic {key}") & _ID_MASK
        if "polymorphic_name" in value:
            names[type_id] = _string(path, value, "polymorphic_name", f"intrinsic {key}")
        model = names.get(type_id)
        if model is None:
            raise InputError(path, f"intrinsic {key}: polymorphic_id {type_id} has no polymorphic_name before it")
        result[key] = _intrinsic(path, key, model, _pointer_data(path, value, pointers, f"intrinsic {key}"))
    return result


def _intrinsic(path: Path, key: int, model: str, data: dict) -> tuple[int, int, np.ndarray, np.ndarray]:
    where = f"intrinsic {key} ({model})"
    if model not in _DISTORTION_KEYS:
        raise InputError(path, f"{where}: camera model not supported; expected one of "
                               f"{', '.join(_DISTORTION_KEYS)} (fisheye and spherical views need undistorting)")
    f = _numbers(path, [_field(path, data, "focal_length", where)], 1, f"{where} focal_length")[0]
    cx, cy = _numbers(path, _field(path, data, "principal_point", where), 2, f"{where} principal_point")
    width, height = (_index(path, data, k, where) for k in ("width", "height"))
    key_name = _DISTORTION_KEYS[model]
    coeffs = [] if key_name is None else _numbers(path, _field(path, data, key_name, where),
                                                  {"disto_k1": 1, "disto_k3": 3, "disto_t2": 5}[key_name],
                                                  f"{where} {key_name}")
    if model == "pinhole_brown_t2":
        k1, k2, k3, t1, t2 = coeffs
        dist = np.array([k1, k2, t1, t2, k3])
    else:
        dist = np.concatenate([coeffs[:2], [0.0, 0.0], coeffs[2:]])
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    return width, height, K, dist


def _pose(path: Path, key: int, entry: dict) -> tuple[np.ndarray, np.ndarray]:
    where = f"extrinsic {key}"
    value = _field(path, entry, "value", where)
    rotation = _field(path, value, "rotation", where)
    if not (isinstance(rotation, list) and len(rotation) == 3):
        raise InputError(path, f"{where}: rotation must be 3 rows of 3 numbers")
    R = np.array([_numbers(path, row, 3, f"{where} rotation") for row in rotation])
    return nearest_rotation(R, path, f"{where} rotation"), _numbers(path, _field(path, value, "center", where), 3,
                                                                   f"{where} center")


def _pointer_data(path: Path, value: dict, pointers: dict[int, dict], where: str) -> dict:
    """The data of a cereal pointer, resolving a repeated pointer to its first occurrence."""
    wrapper = _field(path, value, "ptr_wrapper", where)
    pointer_id = _index(path, wrapper, "id", where) & _ID_MASK
    if "data" in wrapper:
        pointers[pointer_id] = wrapper["data"]
    if pointer_id not in pointers or not isinstance(pointers[pointer_id], dict):
        raise InputError(path, f"{where}: ptr_wrapper id {pointer_id} has no data before it")
    return pointers[pointer_id]


def _index(path: Path, obj: object, key: str, where: str) -> int:
    """An unsigned 32-bit integer field: cereal's ids and sizes, openMVG's IndexT."""
    value = _field(path, obj, key, where)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= _MAX_INDEX:
        raise InputError(path, f"{where}: field {key!r} is {value!r:.80}, expected an integer from 0 to {_MAX_INDEX}")
    return value


def _new_key(path: Path, entry: object, seen: dict[int, object], what: str) -> int:
    """The key of a cereal map entry, refused if an earlier entry had it (one would silently win)."""
    key = _index(path, entry, "key", what)
    if key in seen:
        raise InputError(path, f"{what} key {key} appears twice; expected unique keys")
    return key


def _string(path: Path, obj: dict, key: str, where: str, default: str | None = None) -> str:
    """A string field, or `default` if absent and one is given."""
    value = _field(path, obj, key, where) if default is None else obj.get(key, default)
    if not isinstance(value, str):
        raise InputError(path, f"{where}: field {key!r} is {value!r:.80}, expected a string")
    return value


def _field(path: Path, obj: object, key: str, where: str):
    if not isinstance(obj, dict) or key not in obj:
        raise InputError(path, f"{where}: missing field {key!r}")
    return obj[key]


def _numbers(path: Path, values: object, count: int, where: str) -> np.ndarray:
    if not (isinstance(values, list) and len(values) == count and all(map(is_json_number, values))):
        raise InputError(path, f"{where}: expected {count} finite numbers, found {values!r:.80}")
    return np.array(values, dtype=float)
