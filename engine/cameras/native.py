"""tracemap's own camera file: JSON holding cameras already in our convention (DESIGN.md), losslessly.

    {"format": "tracemap-cameras", "version": 1, "cameras": [Camera.to_dict(), ...]}

Floats are written by `json` with repr precision, so a written and re-read camera is bit-identical.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path

from engine.cameras.camera import Camera, make_camera
from engine.cameras.text import load_json
from engine.errors import InputError

FORMAT = "tracemap-cameras"
VERSION = 1
_FIELDS = ("name", "width", "height", "K", "distortion", "R", "t")


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
    try:
        return make_camera(path, str(entry["name"]), int(entry["width"]), int(entry["height"]), entry["K"],
                           entry["distortion"], entry["R"], entry["t"], entry.get("image_path"))
    except (TypeError, ValueError) as error:
        raise InputError(path, f"{where} ({entry.get('name')!r}): expected numbers in width, height, K, "
                               f"distortion, R, t ({error})") from None
