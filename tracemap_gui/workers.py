"""Long engine calls on the thread pool, with progress and cancel, so no window ever freezes.

A `Task` runs `function(*args, progress=callback, **kwargs)` on `QThreadPool.globalInstance()`. The engine
calls the callback now and then; the task forwards it to the GUI thread as a signal (at most every 50 ms,
so a chatty engine cannot flood the event loop) and raises `engine.errors.Cancelled` from it once Cancel was
pressed. The result, the error or the cancellation arrives as a signal in the GUI thread. Tasks must not
touch the project's SQLite connection (it belongs to the GUI thread): they take data and return data, and
the GUI thread stores the result with an undoable command. A task that writes much opens a connection of
its own (`Project.for_thread`): `Session.push_in_background` for edits, the maps panel for its maps.

A task lets go of everything once it has ended, or every task with its inputs (traces, plots, meshes) is
kept for good, as they were up to session 15: the pool is handed the task's `run`, not the task (PySide6
keeps a QRunnable the pool does not delete), the call's arguments are dropped when it returns, and the
signals, connections and all, are deleted once every slot of `ended` has run in the GUI thread (slots are
often lambdas holding the task: a cycle through Qt's connection, where the garbage collector cannot see it).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from PySide6.QtCore import QObject, QThreadPool, Signal
from PySide6.QtWidgets import QHBoxLayout, QLabel, QProgressBar, QPushButton, QWidget

from engine.errors import Cancelled, Progress
from engine.mesh import first_hit

if TYPE_CHECKING:
    from engine.mesh import Mesh

PROGRESS_INTERVAL = 0.05  # seconds between progress signals


class _Signals(QObject):
    progress = Signal(float, str)
    done = Signal(object)  # the function's result
    failed = Signal(object)  # the exception
    cancelled = Signal()
    ended = Signal()  # after any of the three above
    _result = Signal(object)  # from the worker; becomes `done`, or `cancelled` if cancelled meanwhile
    _stopped = Signal(object)  # from the worker: the exception, `Cancelled` included

    def __init__(self, cancel: threading.Event):
        super().__init__()
        self._cancel = cancel
        self._result.connect(self._deliver)
        self._stopped.connect(self._stop)

    # Both run in the GUI thread, so a Cancel pressed while the result was on its way still drops it, and
    # every slot of `ended` has run before the signals are deleted.
    def _deliver(self, result: object) -> None:
        if self._cancel.is_set():
            self.cancelled.emit()
        else:
            self.done.emit(result)
        self._end()

    def _stop(self, exc: BaseException) -> None:
        if isinstance(exc, Cancelled):
            self.cancelled.emit()
        else:
            self.failed.emit(exc)
        self._end()

    def _end(self) -> None:
        self.ended.emit()
        self.deleteLater()


class Task:
    """One background call. Connect to `signals` before starting it with `Jobs.start` (or a pool's
    `start(task.run)`)."""

    def __init__(self, title: str, function: Callable, *args: object, **kwargs: object):
        self.title = title
        self._cancel = threading.Event()
        self.signals = _Signals(self._cancel)
        self._call = (function, args, kwargs)
        self._last = 0.0

    def cancel(self) -> None:
        """Ask the task to stop at its next progress report; a result it still makes is dropped."""
        self._cancel.set()

    def run(self) -> None:
        function, args, kwargs = self._call
        self._call = None
        try:
            result = function(*args, progress=self._progress, **kwargs)
        except BaseException as exc:  # noqa: BLE001 - delivered to the GUI thread, which shows it
            self.signals._stopped.emit(exc)
        else:
            self.signals._result.emit(result)

    def _progress(self, fraction: float, message: str) -> None:
        if self._cancel.is_set():
            raise Cancelled
        now = time.monotonic()
        if now - self._last >= PROGRESS_INTERVAL or fraction >= 1.0:
            self._last = now
            self.signals.progress.emit(fraction, message)


class Jobs(QObject):
    """The background tasks of a session: starts them and knows which still run."""

    started = Signal(object)  # the Task
    busy = Signal(bool)

    def __init__(self, parent: QObject | None = None):
        super().__init__(parent)
        self._running: list[Task] = []

    @property
    def running(self) -> list[Task]:
        return list(self._running)

    def start(self, task: Task) -> Task:
        self._running.append(task)
        task.signals.ended.connect(self._ended)  # not a lambda holding the task: PySide6 6.7 may keep it
        if len(self._running) == 1:
            self.busy.emit(True)
        self.started.emit(task)
        QThreadPool.globalInstance().start(task.run)
        return task

    def cancel_all(self, wait_ms: int = 0) -> None:
        """Stop every task; none of them delivers a result any more. Wait up to `wait_ms` for them to end."""
        for task in self._running:
            task.cancel()
        if wait_ms and self._running:
            QThreadPool.globalInstance().waitForDone(wait_ms)

    def _ended(self) -> None:
        self._running = [task for task in self._running if task.signals is not self.sender()]
        if not self._running:
            self.busy.emit(False)


class ProgressPanel(QWidget):
    """Title, progress bar and Cancel for the latest running task; hidden while nothing runs."""

    def __init__(self, jobs: Jobs, parent: QWidget | None = None):
        super().__init__(parent)
        self._label = QLabel()
        self._bar = QProgressBar()
        self._bar.setRange(0, 1000)
        self._bar.setMaximumWidth(160)
        self._cancel = QPushButton("Cancel")
        self._cancel.setObjectName("cancel-task")
        layout = QHBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        for widget in (self._label, self._bar, self._cancel):
            layout.addWidget(widget)
        self._task: Task | None = None
        self._cancel.clicked.connect(self._cancel_task)
        jobs.started.connect(self._follow)
        jobs.busy.connect(self._busy)
        self.hide()

    def _busy(self, busy: bool) -> None:
        self.setVisible(busy)
        if not busy:
            self._task = None  # an ended task is let go of (module docstring)

    def _follow(self, task: Task) -> None:
        self._task = task
        self._label.setText(task.title)
        self._bar.setValue(0)
        self._cancel.setEnabled(True)
        # a bound method, not a lambda: Qt drops the connection when the panel is deleted first
        task.signals.progress.connect(self._show_progress)

    def _show_progress(self, fraction: float, message: str) -> None:
        if self._task is None or self.sender() is not self._task.signals:  # an older task: show the latest
            return
        self._bar.setValue(round(fraction * 1000))
        self._label.setText(f"{self._task.title}: {message}")

    def _cancel_task(self) -> None:
        if self._task is not None:
            self._task.cancel()
            self._label.setText(f"{self._task.title}: cancelling…")
            self._cancel.setEnabled(False)


def pick_mesh(mesh: Mesh, origin: np.ndarray, direction: np.ndarray, *, progress: Progress) -> np.ndarray | None:
    """A Task's function: the first point of the mesh on a line of sight (`SceneView.line_of_sight`), or None.
    On a worker, because the first pick builds the mesh's face k-d tree (seconds on millions of faces)."""
    progress(0.0, "picking the mesh")
    return first_hit(mesh, origin, direction)
