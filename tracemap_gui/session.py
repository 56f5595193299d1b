"""The open project as the windows see it: one engine `Project`, one undo stack, and change signals.

The engine project is the model and knows nothing of Qt. Every edit is a `commands.ProjectCommand` pushed
here; it runs as one project transaction (written on a worker for the big ones: `push_in_background`), so
what is on screen is on disk, and the session then tells every window what changed. Reads are cached per
photo because views redraw on every change; the 3D traces are first read on a worker after opening.
"""

from __future__ import annotations

import gc
import threading
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import QObject, QTimer, Signal
from PySide6.QtGui import QUndoStack

from engine.cameras import Camera
from engine.errors import Cancelled, Progress, ProjectError, report
from engine.project import Project
from engine.register import Similarity
from engine.traces import KINDS, Trace2D, Trace3D, check_kind
from tracemap_gui.error_dialog import describe
from tracemap_gui.mesh_tracer import MeshTracer
from tracemap_gui.undo_memory import UNDO_MEMORY, UndoMemory
from tracemap_gui.workers import Jobs, Task

if TYPE_CHECKING:
    from tracemap_gui.commands import ProjectCommand

Trace = Trace2D | Trace3D
_UNSET = object()
KIND_SETTING = "trace_kind"
CLOSE_WAIT_MS = 5000  # on closing, how long to wait for background work to notice it was cancelled


class Session(QObject):
    """One open project (or none) shared by the image editor and the 3D viewer."""

    opened = Signal()  # a project was opened: windows reload everything
    closed = Signal()
    traces2d_changed = Signal(str)  # the 2D traces of this photo changed
    traces3d_changed = Signal()
    selection_changed = Signal()
    registration_changed = Signal()  # readouts in the registered frame convert anew
    busy = Signal(bool)  # background work started (True) or all of it ended (False)
    failed = Signal(str)  # an undo or redo could not be stored; the message says why
    kind_changed = Signal(str)  # the kind new traces are drawn as

    def __init__(self, parent: QObject | None = None, *, undo_memory: int = UNDO_MEMORY):
        super().__init__(parent)
        self.undo_stack = QUndoStack(self)
        self.undo_memory = UndoMemory(self.undo_stack, undo_memory)  # bytes of traces undo keeps in memory
        self.undo_memory.failed.connect(self.failed)
        self.jobs = Jobs(self)
        self.jobs.busy.connect(self.busy)
        self._project: Project | None = None
        self._cameras: dict[str, Camera] = {}
        self._traces2d: dict[str, list[Trace2D]] = {}
        self._traces3d: list[Trace3D] | None = None
        self._selected2d: frozenset[int] = frozenset()
        self._selected3d: frozenset[int] = frozenset()
        self._writing: _Write | None = None  # the edit `push_in_background` is storing
        self._reading: _Once | None = None  # the 3D traces being read after opening
        self.mesh_tracer = MeshTracer()  # the mesh's ray tracer, shared by every tool

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
    def reading_traces3d(self) -> bool:
        """Whether a worker is reading the 3D traces (after opening): `traces3d()` would wait for it, so a
        window that can draw them later does so (0.1–0.3 s of waiting on a loaded machine)."""
        return self._reading is not None

    @property
    def path(self) -> Path | None:
        return None if self._project is None else self._project.path

    def open(self, path: str | Path) -> None:
        """Open a project (closing the current one); a `TracemapError` says why it cannot be opened."""
        self.close()
        project = Project.open(path)
        try:
            self._cameras = project.cameras()
        except BaseException:
            project.close()
            raise
        self._project = project
        self.opened.emit()
        QTimer.singleShot(0, self, self._settle)

    def _settle(self) -> None:
        """After opening, in a pass of the event loop of its own (not the one in which every window reloads):
        read the 3D traces on a worker (0.1–0.4 s of the GUI thread on a loaded machine); `_settled` follows."""
        if not self.is_open:
            return
        if self._traces3d is not None:  # a window read them already
            self._settled(None)
            return
        read = self._reading = _Once(lambda project: project.traces3d(), self.project)
        task = Task("Reading the 3D traces", read.run)
        task.signals.ended.connect(lambda: self._settled(read))
        self.jobs.start(task)

    def _settled(self, read: _Once | None) -> None:
        """The traces read: cache them (unless taken or made stale meanwhile), then take what is alive now
        (modules, windows, the project's traces: 400,000 objects with the demo) out of the garbage collector's
        full passes, which hold the GIL 0.1–0.3 s and froze the window whichever thread ran them. Garbage
        frozen is kept for good: the young generations are swept first (a full sweep here would be the very
        freeze avoided)."""
        if read is not None and read is self._reading:  # else taken by `traces3d`, or stale after an edit
            self._reading = None
            if read.error is None and self._traces3d is None:
                self._traces3d = read.result
        if not self.is_open:
            return
        gc.collect(1)
        gc.freeze()

    def close(self) -> None:
        if self._project is None:
            return
        self._finish_writing()  # an edit being stored is kept
        self.jobs.cancel_all(CLOSE_WAIT_MS)  # their results would belong to a closed project
        self.undo_stack.clear()  # commands hold traces of this project
        self.undo_memory.close()
        self._project.close()
        self._project = None
        self._cameras, self._traces2d, self._traces3d, self._reading = {}, {}, None, None
        self._selected2d = self._selected3d = frozenset()
        self.mesh_tracer.clear()
        self.closed.emit()

    # -- reading --------------------------------------------------------------------------------------

    def images(self) -> list[str]:
        return sorted(self._cameras)

    def camera(self, image: str) -> Camera:
        """The camera of a photo, in the project's local frame."""
        return self._cameras[image]

    def cameras(self) -> dict[str, Camera]:
        return dict(self._cameras)

    def similarity(self) -> Similarity | None:
        """The project's registration, which the viewer's readouts report in as exports do; None without one."""
        registration = self.project.registration() if self.is_open else None
        return None if registration is None else registration.similarity

    def traces2d(self, image: str) -> list[Trace2D]:
        """The 2D traces on one photo, by id. Shared and cached: copy a trace before changing it."""
        if self._writing is not None and self._writing.command.dimension == 2:
            self._finish_writing()  # what is read (e.g. to make the next edit of) includes the edit being stored
        if image not in self._traces2d:
            self._traces2d[image] = self.project.traces2d([image])
        return self._traces2d[image]

    def traces3d(self) -> list[Trace3D]:
        """Every 3D trace, by id. Shared and cached: copy a trace before changing it."""
        self._finish_writing()  # every edit of 2D traces may remove 3D traces too
        if self._traces3d is None:
            read, self._reading = self._reading, None
            if read is not None:  # wait for the worker's read, or read here if it has not started
                read.finish()
            self._traces3d = read.result if read is not None and read.error is None else self.project.traces3d()
        return self._traces3d

    def setting(self, key: str, default: object = None) -> object:
        return default if self._project is None else self._project.setting(key, default)

    @property
    def kind(self) -> str:
        """The kind new traces are drawn as (`engine.traces.KINDS`), kept with the project."""
        kind = self.setting(KIND_SETTING, "fracture")
        return kind if kind in KINDS else "fracture"

    def set_kind(self, kind: str) -> None:
        self.set_setting(KIND_SETTING, check_kind(kind))
        self.kind_changed.emit(kind)

    def set_setting(self, key: str, value: object) -> None:
        """Store a setting; an unchanged one is not written again (each write is a commit, on the GUI thread)."""
        if self._project is not None and self._project.setting(key, _UNSET) != value:
            self._project.set_setting(key, value)

    # -- editing --------------------------------------------------------------------------------------

    def push(self, command: ProjectCommand) -> None:
        """Apply an edit and put it on the undo stack; if it raises, nothing was stored or pushed."""
        self._finish_writing()
        command.apply()
        self.undo_stack.push(command)

    def push_in_background(self, command: ProjectCommand) -> Task:
        """Apply an edit as `push` does, its transaction written on a worker: an extraction of hundreds of
        traces writes tens of MB, 0.1–0.3 s that froze the window. The caches, the windows and the undo
        stack follow once it is stored; until then every push, and every read of the traces it changes,
        waits for it, so edits keep their order on disk and in the undo stack, and none is made from traces
        it replaces. Cancel stores nothing if pressed before the write starts and is ignored after. A
        failure (nothing stored) is reported through `failed`. For the trace commands: those doing more after
        storing (their own `_store`) go through `push`."""
        self._finish_writing()
        write = self._writing = _Write(command, self.project)
        task = Task(command.text(), write.run)
        task.signals.ended.connect(lambda: self._written(write))
        return self.jobs.start(task)

    def _finish_writing(self) -> None:
        """Wait for the edit being stored (or store it here if no worker has taken it yet) and deliver it."""
        if self._writing is not None:
            self._writing.finish()
            self._written(self._writing)

    def _written(self, write: _Write) -> None:
        if write is not self._writing:  # delivered already (or the project was closed meanwhile)
            return
        self._writing = None
        if write.error is None:
            write.command.applied(write.result)
            self.undo_stack.push(write.command)
        elif not isinstance(write.error, Cancelled):
            self.failed.emit(f"{write.command.text()}: {describe(write.error)}")

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
            self._reading = None  # a read still running may have missed this edit
            self.traces3d_changed.emit()
            self.select3d(self._selected3d - gone)

    def reload(self) -> None:
        """Read everything again, after the project was changed behind the session's back (e.g. analysis)."""
        self._traces2d, self._traces3d, self._reading = {}, None, None
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


class _Once:
    """One call of `work(project)` on whichever thread comes first: the worker of its task (through a
    connection of its own), or the GUI thread needing the result now (`finish`, through the session's).
    Qt is not touched here."""

    def __init__(self, work: Callable[[Project], object], project: Project):
        self._work, self._project = work, project
        self.result: object = None
        self.error: BaseException | None = None
        self._claimed = threading.Lock()
        self._done = threading.Event()

    def run(self, *, progress: Progress) -> None:
        """On a worker: the call through the worker's own connection to the project."""
        if self._claimed.acquire(blocking=False):
            try:
                report(progress, 0.0, "starting")  # a Cancel pressed before now leaves it undone
                handle = self._project.for_thread()
                try:
                    self.result = self._work(handle)
                finally:
                    handle.close()
            except BaseException as exc:  # noqa: BLE001 - delivered by the session on the GUI thread
                self.error = exc
            finally:
                self._done.set()

    def finish(self) -> None:
        """On the GUI thread: wait for the worker's call, or make it here through the session's connection."""
        if self._claimed.acquire(blocking=False):
            try:
                self.result = self._work(self._project)
            except Exception as exc:  # noqa: BLE001 - delivered by the session
                self.error = exc
            finally:
                self._done.set()
        self._done.wait()


class _Write(_Once):
    """The first application of a command (its transaction): `result` is its list of `Change`s."""

    def __init__(self, command: ProjectCommand, project: Project):
        super().__init__(command.write, project)
        self.command = command


def _merged(cached: list[Trace], removed: Sequence[Trace], stored: Sequence[Trace]) -> list[Trace]:
    """The cached traces after an edit, still in id order."""
    replaced = {t.id for t in removed} | {t.id for t in stored}
    return sorted([t for t in cached if t.id not in replaced] + list(stored), key=lambda t: t.id)
