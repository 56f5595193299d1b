"""tracemap's own camera file: JSON holding cameras already in our convention (DESIGN.md), losslessly.

    {"format": "tracemap-cameras", "version": 1, "cameras": [Camera.to_dict(), ...]}

Floats are written by `json` with repr precision, so a written and re-read camera is bit-identical.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from engine.cameras.camera import N_DIST, Camera, make_camera
from engine.cameras.text import is_json_number, load_json
from engine.errors import InputError

FORMAT = "tracemap-cameras"
VERSION = 1
_FIELDS = ("name", "width", "height", "K", "distortion", "R", "t")
_ARRAYS = {"K": (3, 3), "distortion": (None, None), "R": (3, 3), "t": (None, 3)}
"""Field → (rows, or None for a flat list; numbers per row, or None for up to N_DIST)."""


def read_native(path: Path) -> dict[str, Camera]:
    """Cameras of a tracemap-cameras JSON file."""
    data = load_json(path)
    if data.get("format") != FORMAT:
        raise InputError(path, f"field 'format' is {data.get('format')!r}, expected {FORMAT!r}")
    if data.get("version") != VERSION:
        raise InputError(path, f"field 'version' is {data.get('version')!r}; this program reads version "
                               f"{VERSION} (a newer tracemap may have written it)")
    if not isinstance(data.get("cameras"), list):
        raise InputError(path, "expected a 'cameras' list")
    cameras: dict[str, Camera] = {}
    for index, entry in enumerate(data["cameras"]):
        camera = _camera(path, index, entry)
        if camera.name in cameras:
            raise InputError(path, f"cameras[{index}]: name {camera.name!r} appears twice")
        cameras[camera.name] = camera
    return cameras


def write_cameras_json(cameras: Mapping[str, Camera] | Iterable[Camera], path: str | Path) -> None:
    """Write cameras (a mapping by name, or any iterable) as a tracemap-cameras JSON file."""
    values = cameras.values() if isinstance(cameras, Mapping) else cameras
    document = {"format": FORMAT, "version": VERSION, "cameras": [camera.to_dict() for camera in values]}
    Path(path).write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")


def _camera(path: Path, index: int, entry: object) -> Camera:
    where = f"cameras[{index}]"
    if not isinstance(entry, dict):
        raise InputError(path, f"{where}: expected an object with fields {', '.join(_FIELDS)}")
    missing = [field for field in _FIELDS if field not in entry]
    if missing:
        raise InputError(path, f"{where}: missing field(s) {', '.join(missing)}")
    name, image_path = entry["name"], entry.get("image_path")
    if not isinstance(name, str) or not name:
        raise InputError(path, f"{where}: field 'name' is {name!r:.80}, expected a non-empty string")
    where = f"{where} ({name!r})"
    if image_path is not None and not isinstance(image_path, str):
        raise InputError(path, f"{where}: field 'image_path' is {image_path!r:.80}, expected a string or null")
    for key in ("width", "height"):
        if isinstance(entry[key], bool) or not isinstance(entry[key], int) or entry[key] <= 0:
            raise InputError(path, f"{where}: field {key!r} is {entry[key]!r:.80}, expected a positive integer "
                                   "(pixels)")
    arrays = {key: _array(path, where, key, entry[key]) for key in _ARRAYS}
    return make_camera(path, name, entry["width"], entry["height"], image_path=image_path, **arrays)


def _array(path: Path, where: str, key: str, value: object) -> np.ndarray:
    """Field `key` as the numbers _ARRAYS says it holds."""
    rows, count = _ARRAYS[key]
    if rows is None:
        ok = _numbers(value, count)
    else:
        ok = isinstance(value, list) and len(value) == rows and all(_numbers(row, count) for row in value)
    if not ok:
        expected = f"{count or f'at most {N_DIST}'} finite numbers"
        raise InputError(path, f"{where}: field {key!r} is {value!r:.80}, expected "
                               + (expected if rows is None else f"{rows} rows of {expected}"))
    return np.array(value, dtype=float)


def _numbers(value: object, count: int | None) -> bool:
    """A list of finite JSON numbers: `count` of them, or up to N_DIST if None."""
    return (isinstance(value, list) and (len(value) == count if count else len(value) <= N_DIST)
            and all(map(is_json_number, value)))
