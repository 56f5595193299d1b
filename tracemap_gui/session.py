"""The open project as the windows see it: one engine `Project`, one undo stack, and change signals.

The engine project is the model and knows nothing of Qt. Every edit is a `commands.ProjectCommand` pushed
here; it runs as one project transaction, so what is on screen is on disk, and the session then tells every
window what changed. Reads are cached per photo because views redraw on every change.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import QObject, Signal
from PySide6.QtGui import QUndoStack

from engine.cameras import Camera
from engine.errors import ProjectError
from engine.project import Project
from engine.traces import Trace2D, Trace3D
from tracemap_gui.workers import Jobs

if TYPE_CHECKING:
    from tracemap_gui.commands import ProjectCommand

Trace = Trace2D | Trace3D
CLOSE_WAIT_MS = 5000  # on closing, how long to wait for background work to notice it was cancelled


class Session(QObject):
    """One open project (or none) shared by the image editor and the 3D viewer."""

    opened = Signal()  # a project was opened: windows reload everything
    closed = Signal()
    traces2d_changed = Signal(str)  # the 2D traces of this photo changed
    traces3d_changed = Signal()
    selection_changed = Signal()
    busy = Signal(bool)  # background work started (True) or all of it ended (False)
    failed = Signal(str)  # an undo or redo could not be stored; the message says why

    def __init__(self, parent: QObject | None = None):
        super().__init__(parent)
        self.undo_stack = QUndoStack(self)
        self.jobs = Jobs(self)
        self.jobs.busy.connect(self.busy)
        self._project: Project | None = None
        self._cameras: dict[str, Camera] = {}
        self._traces2d: dict[str, list[Trace2D]] = {}
        self._traces3d: list[Trace3D] | None = None
        self._selected2d: frozenset[int] = frozenset()
        self._selected3d: frozenset[int] = frozenset()

    # -- opening and closing --------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        return self._project is not None

    @property
    def project(self) -> Project:
        if self._project is None:
            raise ProjectError("no project is open; use File → Open")
        return self._project

    @property
    def path(self) -> Path | None:
        return None if self._project is None else self._project.path

    def open(self, path: str | Path) -> None:
        """Open a project (closing the current one); a `TracemapError` says why it cannot be opened."""
        self.close()
        project = Project.open(path)
        try:
            self._cameras = project.cameras()
            self._traces3d = project.traces3d()  # read now, not in the middle of the first extraction
        except BaseException:
            project.close()
            raise
        self._project = project
        self.opened.emit()

    def close(self) -> None:
        if self._project is None:
            return
        self.jobs.cancel_all(CLOSE_WAIT_MS)  # their results would belong to a closed project
        self.undo_stack.clear()  # commands hold traces of this project
        self._project.close()
        self._project = None
        self._cameras, self._traces2d, self._traces3d = {}, {}, None
        self._selected2d = self._selected3d = frozenset()
        self.closed.emit()

    # -- reading --------------------------------------------------------------------------------------

    def images(self) -> list[str]:
        return sorted(self._cameras)

    def camera(self, image: str) -> Camera:
        """The camera of a photo, in the project's local frame."""
        return self._cameras[image]

    def cameras(self) -> dict[str, Camera]:
        return dict(self._cameras)

    def traces2d(self, image: str) -> list[Trace2D]:
        """The 2D traces on one photo, by id. Shared and cached: copy a trace before changing it."""
        if image not in self._traces2d:
            self._traces2d[image] = self.project.traces2d([image])
        return self._traces2d[image]

    def traces3d(self) -> list[Trace3D]:
        """Every 3D trace, by id. Shared and cached: copy a trace before changing it."""
        if self._traces3d is None:
            self._traces3d = self.project.traces3d()
        return self._traces3d

    def setting(self, key: str, default: object = None) -> object:
        return default if self._project is None else self._project.setting(key, default)

    def set_setting(self, key: str, value: object) -> None:
        if self._project is not None:
            self._project.set_setting(key, value)

    # -- editing --------------------------------------------------------------------------------------

    def push(self, command: ProjectCommand) -> None:
        """Apply an edit and put it on the undo stack; if it raises, nothing was stored or pushed."""
        command.apply()
        self.undo_stack.push(command)

    def stored(self, dimension: int, removed: Sequence[Trace], stored: Sequence[Trace]) -> None:
        """Called by commands after their transaction: bring the caches up to date and tell the windows.

        removed : the traces the edit deleted; stored : those it added or changed (with their ids).
        """
        gone = {t.id for t in removed} - {t.id for t in stored}
        if dimension == 2:
            images = sorted({t.image for t in (*removed, *stored)})
            for image in images:
                if image in self._traces2d:
                    self._traces2d[image] = _merged(self._traces2d[image], removed,
                                                    [t for t in stored if t.image == image])
                self.traces2d_changed.emit(image)
            self.select2d(self._selected2d - gone)
        else:
            if self._traces3d is not None:
                self._traces3d = _merged(self._traces3d, removed, stored)
            self.traces3d_changed.emit()
            self.select3d(self._selected3d - gone)

    def reload(self) -> None:
        """Read everything again, after the project was changed behind the session's back (e.g. analysis)."""
        self._traces2d, self._traces3d = {}, None
        for image in self.images():
            self.traces2d_changed.emit(image)
        self.traces3d_changed.emit()

    # -- selection ------------------------------------------------------------------------------------

    @property
    def selected2d(self) -> frozenset[int]:
        return self._selected2d

    @property
    def selected3d(self) -> frozenset[int]:
        return self._selected3d

    def select2d(self, ids: Iterable[int]) -> None:
        ids = frozenset(int(i) for i in ids)
        if ids != self._selected2d:
            self._selected2d = ids
            self.selection_changed.emit()

    def select3d(self, ids: Iterable[int]) -> None:
        ids = frozenset(int(i) for i in ids)
        if ids != self._selected3d:
            self._selected3d = ids
            self.selection_changed.emit()


def _merged(cached: list[Trace], removed: Sequence[Trace], stored: Sequence[Trace]) -> list[Trace]:
    """The cached traces after an edit, still in id order."""
    replaced = {t.id for t in removed} | {t.id for t in stored}
    return sorted([t for t in cached if t.id not in replaced] + list(stored), key=lambda t: t.id)
