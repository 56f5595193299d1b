"""Which camera format a path holds, decided from the content (magic bytes, headers, root keys).

Extensions lie (.txt, .json and .xml are shared by many tools), so the first bytes decide; the file name
is used only where a format has no signature: COLMAP .bin files and headerless (version 0) OpenMVS files.
"""

from __future__ import annotations

import re
from pathlib import Path

from engine.cameras import colmap, openmvs
from engine.errors import InputError

FORMATS = ("colmap", "metashape", "bundler", "nvm", "openmvg", "openmvs", "tracemap")
_HEAD_BYTES = 4096
_COLMAP_HEADERS = ("# Camera list with one line of data per camera", "# Image list with two lines of data")
_COLMAP_NAMES = ("cameras.txt", "images.txt", "cameras.bin", "images.bin")
_TRACEMAP_KEY = re.compile(r'"format"\s*:\s*"tracemap-cameras"')
_EXPECTED = ("a COLMAP model folder or file, Metashape cameras XML, Bundler .out, VisualSFM .nvm, "
             "OpenMVG sfm_data.json, OpenMVS .mvs or tracemap cameras JSON")


def detect_format(path: str | Path) -> str:
    """One of FORMATS, or InputError saying what was expected."""
    path = Path(path)
    if path.is_dir():
        if colmap.model_files(path) is not None:
            return "colmap"
        raise InputError(path, f"folder holds no cameras.txt/images.txt or cameras.bin/images.bin; expected "
                               f"{_EXPECTED}")
    if not path.is_file():
        raise InputError(path, "no such file or folder")
    try:
        with path.open("rb") as stream:
            head = stream.read(_HEAD_BYTES)
    except OSError as error:
        raise InputError(path, f"cannot read the file: {error.strerror}") from None
    found = _from_head(head) or _from_name(path)
    if found is None:
        raise InputError(path, f"unrecognised camera file; expected {_EXPECTED}")
    return found


def _from_head(head: bytes) -> str | None:
    if head.startswith(openmvs.MAGIC):
        return "openmvs"
    text = head.decode("utf-8", errors="replace").lstrip("\ufeff \t\r\n")
    if text.startswith("NVM_V3"):
        return "nvm"
    if text.startswith("# Bundle file"):
        return "bundler"
    if text.startswith("<") and re.search(r"<document|<chunk", text):
        return "metashape"
    if text.startswith("{"):
        if _TRACEMAP_KEY.search(text):
            return "tracemap"
        if '"sfm_data_version"' in text or '"views"' in text:
            return "openmvg"
    if text.startswith(_COLMAP_HEADERS):
        return "colmap"
    return None


def _from_name(path: Path) -> str | None:
    if path.name in _COLMAP_NAMES and colmap.model_files(path) is not None:
        return "colmap"
    if path.suffix.lower() == ".mvs":
        return "openmvs"
    return None
