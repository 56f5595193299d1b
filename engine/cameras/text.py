"""Text camera files (COLMAP, Bundler, NVM lines; OpenMVG and tracemap JSON) read with errors that name the
file, the line or field, and what was expected.

Every number a line-oriented reader takes goes through `TextLines`, so a malformed file never leaks a bare
ValueError: the user is told which line of which file held what instead of what was expected.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from engine.errors import InputError


def read_text(path: Path) -> str:
    """The whole file as text; undecodable bytes are replaced, since only names can hold them."""
    try:
        return path.read_text(encoding="utf-8", errors="replace")
    except OSError as error:
        raise InputError(path, f"cannot read the file: {error.strerror}") from None


def load_json(path: Path) -> dict:
    """The JSON object in `path`; InputError with the line of a syntax error."""
    try:
        data = json.loads(read_text(path))
    except json.JSONDecodeError as error:
        raise InputError(path, f"line {error.lineno}: not valid JSON ({error.msg})") from None
    if not isinstance(data, dict):
        raise InputError(path, "expected a JSON object at the top level")
    return data


def is_json_number(value: object) -> bool:
    """A finite JSON number: not true or false (Python's bools are ints), nor an integer too large for a float."""
    try:
        return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    except OverflowError:
        return False


class TextLines:
    """The lines of a text file with their 1-based numbers, consumed one at a time."""

    def __init__(self, path: Path, *, skip_blank: bool = True, comment: str | None = "#"):
        self.path = path
        self._lines = [(number, line.strip()) for number, line in enumerate(read_text(path).splitlines(), 1)
                       if not (skip_blank and not line.strip())
                       and not (comment and line.lstrip().startswith(comment))]
        self._next = 0

    def at_end(self) -> bool:
        return self._next >= len(self._lines)

    def next(self, what: str) -> tuple[int, str]:
        """The next line (number, stripped text); InputError saying `what` was expected if the file ended."""
        if self.at_end():
            last = self._lines[-1][0] if self._lines else 0
            raise InputError(self.path, f"the file ends after line {last}; expected {what}")
        line = self._lines[self._next]
        self._next += 1
        return line

    def numbers(self, what: str, count: int | None = None, *, minimum: int | None = None) -> np.ndarray:
        """The next line parsed as floats: exactly `count` of them, or at least `minimum`."""
        number, text = self.next(what)
        return parse_numbers(self.path, number, text.split(), what, count, minimum=minimum)

    def integer(self, what: str) -> int:
        """The next line as one non-negative integer (a count)."""
        return self.counts(what, 1)[0]

    def counts(self, what: str, count: int) -> list[int]:
        """The next line as exactly `count` non-negative integers."""
        number, text = self.next(what)
        tokens = text.split()
        if len(tokens) != count:
            raise InputError(self.path, f"line {number}: expected {what} ({count} integers), found {len(tokens)} "
                                        "values")
        return [parse_count(self.path, number, token, what) for token in tokens]


def parse_numbers(path: Path, line: int, tokens: list[str], what: str, count: int | None = None, *,
                  minimum: int | None = None) -> np.ndarray:
    """Floats from `tokens`; InputError naming the line if a token is not a number or the count is wrong."""
    if count is not None and len(tokens) != count:
        raise InputError(path, f"line {line}: expected {what} ({count} values), found {len(tokens)} values")
    if minimum is not None and len(tokens) < minimum:
        raise InputError(path, f"line {line}: expected {what} (at least {minimum} values), "
                               f"found {len(tokens)} values")
    try:
        values = np.array([float(token) for token in tokens])
    except ValueError:
        bad = next(token for token in tokens if not _is_float(token))
        raise InputError(path, f"line {line}: expected {what}, found non-numeric value {bad!r}") from None
    if not np.all(np.isfinite(values)):
        raise InputError(path, f"line {line}: expected {what}, found a non-finite value")
    return values


def parse_count(path: Path, line: int, token: str, what: str) -> int:
    """A non-negative integer (a count or an index), or InputError naming the line."""
    try:
        value = int(token)
    except ValueError:
        raise InputError(path, f"line {line}: expected {what} (an integer), found {token!r}") from None
    if value < 0:
        raise InputError(path, f"line {line}: expected {what} (an integer >= 0), found {value}")
    return value


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True
