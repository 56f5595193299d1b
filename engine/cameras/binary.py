"""Little-endian binary camera files (COLMAP .bin, OpenMVS .mvs) read with errors that name file and offset.

A truncated or corrupt file must say where it broke and what was expected, never leak a struct.error; and a
corrupt count must not make a reader loop over billions of phantom entries, hence `count`.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from engine.errors import InputError


def read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as error:
        raise InputError(path, f"cannot read the file: {error.strerror}") from None


class BinaryReader:
    """A cursor over the bytes of `path`; every read states what it expected."""

    def __init__(self, path: Path, data: bytes | None = None, offset: int = 0):
        self.path = path
        self.data = read_bytes(path) if data is None else data
        self.offset = offset

    @property
    def remaining(self) -> int:
        return len(self.data) - self.offset

    def unpack(self, fmt: str, what: str) -> tuple:
        """Values of the little-endian struct format `fmt`."""
        size = struct.calcsize("<" + fmt)
        if size > self.remaining:
            raise InputError(self.path, f"truncated at byte {self.offset}: expected {what} ({size} bytes), "
                                        f"only {self.remaining} bytes left")
        values = struct.unpack_from("<" + fmt, self.data, self.offset)
        self.offset += size
        return values

    def doubles(self, count: int, what: str) -> np.ndarray:
        """`count` float64 values, which must be finite."""
        start = self.offset
        values = np.array(self.unpack(f"{count}d", what))
        if not np.all(np.isfinite(values)):
            raise InputError(self.path, f"byte {start}: expected {what} as finite numbers, found {values.tolist()}")
        return values

    def skip(self, size: int, what: str) -> None:
        if size > self.remaining:
            raise InputError(self.path, f"truncated at byte {self.offset}: expected {what} ({size} bytes), "
                                        f"only {self.remaining} bytes left")
        self.offset += size

    def count(self, fmt: str, min_item_size: int, what: str) -> int:
        """An element count, checked against the bytes left (each element needs `min_item_size` bytes)."""
        start = self.offset
        (n,) = self.unpack(fmt, f"the number of {what}")
        if n * min_item_size > self.remaining:
            raise InputError(self.path, f"byte {start}: the file claims {n} {what}, but only "
                                        f"{self.remaining} bytes are left (corrupt or truncated file)")
        return n

    def cstring(self, what: str) -> str:
        """A NUL-terminated UTF-8 string (COLMAP image names)."""
        end = self.data.find(b"\0", self.offset)
        if end < 0:
            raise InputError(self.path, f"truncated at byte {self.offset}: expected {what} ending in a NUL byte")
        text = self.data[self.offset:end].decode("utf-8", errors="replace")
        self.offset = end + 1
        return text

    def sized_string(self, what: str) -> str:
        """A UTF-8 string preceded by its uint64 length (OpenMVS std::string)."""
        size = self.count("Q", 1, f"bytes in {what}")
        text = self.data[self.offset:self.offset + size].decode("utf-8", errors="replace")
        self.offset += size
        return text
