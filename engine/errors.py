"""Errors the engine raises, and the progress/cancel protocol of long operations.

Every error a user can cause is a `TracemapError` whose message names the file, the field and what was
expected; the CLI and the GUI show the message and never a traceback.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

Progress = Callable[[float, str], None]
"""A progress callback: fraction done in [0, 1] and a short message. It may raise `Cancelled` to stop."""


class TracemapError(Exception):
    """Bad input or state that the user can fix; the message says what to fix."""


class InputError(TracemapError):
    """A file or value given to tracemap is missing, unreadable or malformed."""

    def __init__(self, source: str | Path | None, message: str):
        self.source = None if source is None else str(source)
        super().__init__(f"{self.source}: {message}" if self.source else message)


class ProjectError(TracemapError):
    """The project file cannot be opened or changed as asked."""


class Cancelled(Exception):
    """Raised by a progress callback to stop a long operation; nothing is written."""


def report(progress: Progress | None, fraction: float, message: str) -> None:
    """Call `progress` if one was given; a callback that raises `Cancelled` stops the caller."""
    if progress is not None:
        progress(min(max(fraction, 0.0), 1.0), message)
