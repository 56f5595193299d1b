"""The tracemap desktop application (PySide6): the image editor, the 3D viewer and what they share.

The engine project is the model and knows nothing of Qt; `session.Session` wraps it with change signals and
an undo stack, windows observe the session, tools turn mouse gestures into undoable `commands`, and long
engine calls run in `workers`.
"""

import ctypes
import sys

from PySide6.QtCore import QObject


def _keep_none_alive() -> None:
    """Work round PySide6 6.12.0 on Python < 3.12, which takes a reference off None at every call of a C++
    method returning void (1000 `QPen.setWidthF` calls: 1000 fewer). None starts with about 5000, so a window
    would abort with "deallocating None" after a few seconds of painting. Python 3.12 made None immortal
    (PEP 683); where the bug shows, do the same by giving None a reference count no session can use up.
    """
    probe = QObject()
    before = sys.getrefcount(None)
    probe.setObjectName("probe")
    if sys.getrefcount(None) < before:
        ctypes.c_ssize_t.from_address(id(None)).value += 1 << 60  # ob_refcnt is a PyObject's first field


_keep_none_alive()
