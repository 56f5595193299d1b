"""Errors as a person sees them: a dialog saying what to fix, never a traceback.

A `TracemapError` already names the file and what to fix. Anything else is a bug: the dialog gets one line
and the traceback goes to a log file to attach to a report.
"""

from __future__ import annotations

import sys
import tempfile
import traceback
from pathlib import Path
from types import TracebackType

from PySide6.QtCore import Qt
from PySide6.QtWidgets import QApplication, QMessageBox, QWidget

from engine.errors import TracemapError

LOG = Path(tempfile.gettempdir()) / "tracemap-error.log"
_open_dialogs: set[QMessageBox] = set()


def describe(exc: BaseException) -> str:
    """One message for a person: what went wrong and, where we know, what to do."""
    if isinstance(exc, TracemapError):
        return str(exc)
    if isinstance(exc, MemoryError):
        return "out of memory; close other programs or work on fewer photos at once"
    if isinstance(exc, OSError):
        return f"{exc.strerror or exc} ({exc.filename or 'file system'})"
    LOG.write_text("".join(traceback.format_exception(exc)), encoding="utf-8")
    return f"internal error: {exc!r}. Please report it with {LOG}"


def show_error(parent: QWidget | None, doing: str, exc: BaseException | str) -> QMessageBox:
    """A non-blocking error dialog: "<doing> failed" and the message (`exc` or its description)."""
    text = exc if isinstance(exc, str) else describe(exc)
    box = QMessageBox(QMessageBox.Icon.Critical, "tracemap", f"{doing} failed", QMessageBox.StandardButton.Ok,
                      parent or QApplication.activeWindow())
    box.setInformativeText(text)
    box.setObjectName("error-dialog")
    box.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose)
    if box.parent() is None:  # nobody else keeps a parentless dialog alive until it is closed
        _open_dialogs.add(box)
        box.finished.connect(lambda: _open_dialogs.discard(box))
    box.open()  # window-modal but not a nested event loop: work in the background carries on
    return box


def install_excepthook() -> None:
    """Uncaught exceptions in slots become dialogs instead of tracebacks on the terminal."""
    def hook(kind: type[BaseException], exc: BaseException, tb: TracebackType | None) -> None:
        if issubclass(kind, KeyboardInterrupt):
            sys.__excepthook__(kind, exc, tb)
            return
        show_error(None, "The last action", exc)

    sys.excepthook = hook
