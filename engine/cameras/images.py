"""The photos behind the cameras: finding them by name, and reading their pixel size from the header only.

Sizes are read with PIL's lazy `Image.open(...).size` (header only); decoding a 24 MP photo just to learn
its size would make opening a project of hundreds of photos take minutes. The size is that of the stored
pixel grid, before any EXIF rotation.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

from PIL import Image, UnidentifiedImageError

from engine.cameras.camera import Camera
from engine.errors import InputError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")

ImageSizes = tuple[int, int] | Mapping[str, tuple[int, int]]
"""Sizes (width, height) for formats that do not store them: one for all photos, or one per photo name."""


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) in pixels from the image header."""
    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, UnidentifiedImageError, Image.DecompressionBombError) as error:
        raise InputError(path, f"cannot read the image header: {error}") from None


def check_images(cameras: Mapping[str, Camera], image_dir: str | Path) -> dict[str, Path]:
    """The photo of each camera under `image_dir`, checked to have the camera's pixel size.

    A photo is found by the camera's name as a path below `image_dir`, then by file name anywhere below
    it, then by stem with a common image suffix (Metashape labels have no suffix). Every camera without
    a photo is listed in one error, and so is every size mismatch.
    """
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise InputError(image_dir, "not a directory; expected the folder holding the photos")
    index = _PhotoIndex(image_dir)
    found = {name: index.find(name) for name in cameras}
    missing = sorted(name for name, path in found.items() if path is None)
    if missing:
        raise InputError(image_dir, f"no photo found for {len(missing)} of {len(cameras)} cameras: "
                                    f"{_listing(missing)} (looked for the name, the file name and the stem "
                                    f"with {', '.join(IMAGE_SUFFIXES)})")
    mismatched = []
    for name, path in found.items():
        expected, actual = (cameras[name].width, cameras[name].height), image_size(path)
        if actual != expected:
            mismatched.append(f"{path} is {actual[0]}×{actual[1]} px but camera {name!r} is "
                              f"{expected[0]}×{expected[1]}")
    if mismatched:
        raise InputError(image_dir, "photo size differs from its camera: " + "; ".join(mismatched))
    return found


def sizes_for(names: Iterable[str], source: Path, image_sizes: ImageSizes | None,
              image_dir: Path) -> dict[str, tuple[int, int]]:
    """Pixel sizes for a format that does not store them (Bundler, NVM, normalised OpenMVS).

    Given `image_sizes` wins; otherwise each photo is looked up under `image_dir` and its header read.
    """
    names = list(names)
    if image_sizes is not None and not isinstance(image_sizes, Mapping):
        width, height = (int(v) for v in image_sizes)
        return dict.fromkeys(names, (width, height))
    sizes: dict[str, tuple[int, int]] = {}
    index = _PhotoIndex(image_dir) if image_dir.is_dir() else None
    for name in names:
        if image_sizes is not None and (name in image_sizes or Path(name).name in image_sizes):
            sizes[name] = tuple(int(v) for v in image_sizes.get(name, image_sizes.get(Path(name).name)))
        elif index is not None and (path := index.find(name)) is not None:
            sizes[name] = image_size(path)
    missing = [name for name in names if name not in sizes]
    if missing:
        raise InputError(source, f"the file does not store image sizes and no photo was found in {image_dir} "
                                 f"for {_listing(missing)}; put the photos there or give their size "
                                 "(`tracemap new --image-size W H`; image_sizes= in Python)")
    return sizes


class _PhotoIndex:
    """Files below a folder by lower-case file name and by lower-case stem (image suffixes only)."""

    def __init__(self, root: Path):
        self.root = root
        self.by_name: dict[str, list[Path]] = {}
        self.by_stem: dict[str, list[Path]] = {}
        for path in sorted(p for p in root.rglob("*") if p.is_file()):
            self.by_name.setdefault(path.name.lower(), []).append(path)
            if path.suffix.lower() in IMAGE_SUFFIXES:
                self.by_stem.setdefault(path.stem.lower(), []).append(path)

    def find(self, name: str) -> Path | None:
        exact = self.root / name
        if exact.is_file():
            return exact
        base = Path(name.replace("\\", "/")).name
        for table, key in ((self.by_name, base.lower()), (self.by_stem, Path(base).stem.lower()),
                           (self.by_stem, base.lower())):
            candidates = table.get(key, [])
            if len(candidates) > 1:
                raise InputError(self.root, f"camera {name!r} matches several photos: "
                                            f"{_listing([str(p) for p in candidates])}; keep one or rename")
            if candidates:
                return candidates[0]
        return None


def _listing(items: list[str], limit: int = 20) -> str:
    shown = ", ".join(items[:limit])
    return shown + (f" … and {len(items) - limit} more" if len(items) > limit else "")
