"""`tracemap gui`: the application: one session shown in two windows, the image editor and the 3D viewer.

The windows' places on screen are project settings (stored shortly after each move, so a killed program
reopens as it was); the list of recent projects and the undo history's memory budget ("undo_memory_mb") are user settings
(QSettings).
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

from PySide6.QtCore import QByteArray, QEvent, QObject, QSettings, QTimer
from PySide6.QtGui import QAction, QKeySequence
from PySide6.QtWidgets import QApplication, QDoubleSpinBox, QFileDialog, QMainWindow, QMenu, QWidget

from engine.errors import TracemapError
from engine.project import SUFFIX
from tracemap_gui.error_dialog import install_excepthook, show_error
from tracemap_gui.export_dialog import ExportDialog, ExportRequest, export_results
from tracemap_gui.image_editor import ImageEditor
from tracemap_gui.map_window import MapWindow
from tracemap_gui.new_project import NewProject, NewProjectDialog, create_project
from tracemap_gui.project_status import show_status
from tracemap_gui.session import Session
from tracemap_gui.undo_memory import UNDO_MEMORY
from tracemap_gui.value_dialog import ValueDialog
from tracemap_gui.workers import Task

RECENT = 8  # projects in File → Recent
SAVE_GEOMETRY_DELAY_MS = 500


class WindowPlace(QObject):
    """Keeps a main window's geometry and dock layout in a project setting, and restores it on open."""

    def __init__(self, window: QMainWindow, key: str, session: Session):
        super().__init__(window)
        self._window, self._key, self._session = window, key, session
        self._timer = QTimer(self, singleShot=True, interval=SAVE_GEOMETRY_DELAY_MS)
        self._timer.timeout.connect(self.store)
        window.installEventFilter(self)
        session.opened.connect(self.restore)

    def eventFilter(self, watched: QObject, event: QEvent) -> bool:
        if event.type() in (QEvent.Type.Move, QEvent.Type.Resize) and self._session.is_open:
            self._timer.start()
        return False

    def store(self) -> None:
        self._session.set_setting(self._key, {
            "geometry": bytes(self._window.saveGeometry().toBase64()).decode(),
            "state": bytes(self._window.saveState().toBase64()).decode()})

    def restore(self) -> None:
        place = self._session.setting(self._key)
        if place:
            self._window.restoreGeometry(QByteArray.fromBase64(place["geometry"].encode()))
            self._window.restoreState(QByteArray.fromBase64(place["state"].encode()))
        self._timer.stop()  # restoring moved the window: nothing new to store


class Application(QObject):
    """The session, its windows, and the File menu they share (New, Open, Recent, Close, Status, Export,
    Analyse a 2D map, Quit)."""

    def __init__(self, parent: QObject | None = None):
        super().__init__(parent)
        self.session = Session(self, undo_memory=undo_memory_setting())
        self.editor = ImageEditor(self.session)
        self.viewer = self._make_viewer()
        self.windows = [w for w in (self.editor, self.viewer) if w is not None]
        self.map_window: MapWindow | None = None  # File → Analyse a 2D map…, made when first asked for
        self._places = [WindowPlace(self.editor, "editor.window", self.session)]
        if self.viewer is not None:
            self._places.append(WindowPlace(self.viewer, "viewer.window", self.session))
        for window in self.windows:
            self._file_menu(window)
        if self.viewer is not None:
            self.viewer.reveal2d.connect(self.editor.reveal)
            self.editor.look3d.connect(self._look_from)
        else:
            self.editor.look3d_action.setVisible(False)
        QApplication.instance().aboutToQuit.connect(self.session.close)

    def _make_viewer(self) -> QMainWindow | None:
        """The 3D viewer if this installation has one; the editor works alone otherwise."""
        try:
            from tracemap_gui.viewer3d import Viewer3D
        except ModuleNotFoundError as exc:
            if exc.name != "tracemap_gui.viewer3d":
                raise
            return None
        try:
            return Viewer3D(self.session)
        except Exception as exc:  # noqa: BLE001 - e.g. no OpenGL: say so, keep the editor
            show_error(self.editor, "Opening the 3D viewer", exc)
            return None

    def _file_menu(self, window: QMainWindow) -> None:
        menu = getattr(window, "file_menu", None)
        if menu is None:  # a window without one gets it first in its menu bar
            bar = window.menuBar()
            menu = QMenu("&File", window)
            first = bar.actions()
            bar.insertMenu(first[0], menu) if first else bar.addMenu(menu)
        new_action = QAction("&New project…", window, shortcut=QKeySequence.StandardKey.New)
        new_action.setStatusTip("a project from a mesh, a camera file and the photos (tracemap new)")
        new_action.triggered.connect(lambda: self.new_dialog(window))
        open_action = QAction("&Open project…", window, shortcut=QKeySequence.StandardKey.Open)
        open_action.triggered.connect(self.open_dialog)
        recent = QMenu("Open &recent", window)
        recent.aboutToShow.connect(lambda: self._fill_recent(recent))
        close_action = QAction("&Close project", window, shortcut=QKeySequence.StandardKey.Close)
        close_action.setStatusTip("close the project (every edit is already saved)")
        close_action.triggered.connect(self.session.close)
        status_action = QAction("Project &status…", window)
        status_action.setStatusTip("what the project holds, what is out of date, and the next step (tracemap info)")
        status_action.triggered.connect(lambda: show_status(window, self.session))
        export_action = QAction("&Export results…", window)
        export_action.setStatusTip("write the traces, sets, maps and samples for other tools (tracemap export)")
        export_action.triggered.connect(lambda: self.export_dialog(window))
        map_action = QAction("Analyse a 2D &map…", window)
        map_action.setStatusTip("terminations, topology, lengths and P21 of a trace map from a GIS, in a window of "
                                "its own; no project needed (tracemap analyse-map)")
        map_action.triggered.connect(self.show_map_window)
        quit_action = QAction("&Quit", window, shortcut=QKeySequence.StandardKey.Quit)
        quit_action.triggered.connect(QApplication.instance().quit)
        undo_memory = QAction("&Undo memory…", window)
        undo_memory.setToolTip("how much of the undo history's traces to keep in memory; the rest waits on disk")
        undo_memory.triggered.connect(lambda: self.ask_undo_memory(window))
        menu.addAction(new_action)
        menu.addAction(open_action)
        menu.addMenu(recent)
        menu.addAction(close_action)
        menu.addSeparator()
        menu.addAction(status_action)
        menu.addAction(export_action)
        menu.addAction(map_action)
        menu.addSeparator()
        menu.addAction(undo_memory)
        menu.addSeparator()
        menu.addAction(quit_action)
        window.addActions([new_action, open_action, close_action, quit_action])

    def ask_undo_memory(self, parent: QWidget) -> None:
        """Ask for the undo history's memory budget; it applies at once and is kept for later sessions."""
        dialog = UndoMemoryDialog(self.session.undo_memory.budget, parent)
        if dialog.exec() and dialog.values is not None:
            QSettings().setValue("undo_memory_mb", dialog.values / 2**20)
            self.session.undo_memory.budget = dialog.values
            self.session.undo_memory.bound()

    def show_map_window(self) -> MapWindow:
        """The window of 2D-map analysis: made when first asked for, then the same one raised."""
        if self.map_window is None:
            self.map_window = MapWindow()
        self.map_window.show()
        self.map_window.raise_()
        return self.map_window

    def _look_from(self, image: str) -> None:
        self.viewer.look_from(image)
        self.viewer.show()
        self.viewer.raise_()

    def show(self) -> None:
        for window in self.windows:
            window.show()

    # -- opening --------------------------------------------------------------------------------------

    def open(self, path: str | Path) -> bool:
        """Open a project in both windows; a dialog says why if it cannot be opened."""
        try:
            self.session.open(path)
        except TracemapError as exc:
            show_error(self.editor, f"Opening {path}", exc)
            return False
        remember(Path(path))
        return True

    def new_dialog(self, parent: QWidget) -> None:
        dialog = NewProjectDialog(parent)
        if dialog.exec() and dialog.values is not None:
            self.create(dialog.values)

    def create(self, request: NewProject) -> Task:
        """Make the project on a worker, then open it; a dialog says why if it cannot be made."""
        task = Task("Creating the project", create_project, request)
        task.signals.done.connect(self.open)
        task.signals.failed.connect(lambda exc: show_error(self.editor, f"Creating {request.path}", exc))
        self.session.jobs.start(task)
        return task

    def export_dialog(self, parent: QMainWindow) -> None:
        if not self.session.is_open:
            parent.statusBar().showMessage("open a project first", 5000)
            return
        last = self.session.setting("export", {})
        dialog = ExportDialog(last.get("folder", ""), tuple(last.get("formats", ("csv", "ply"))), parent)
        if dialog.exec() and dialog.values is not None:
            self.export(dialog.values, parent)

    def export(self, request: ExportRequest, window: QMainWindow | None = None) -> Task:
        """Export on a worker; the window's status bar says what was written, a dialog why it failed."""
        window = window or self.editor
        self.session.set_setting("export", {"folder": str(request.folder), "formats": list(request.formats)})
        task = Task("Exporting", export_results, self.session.project, request)
        task.signals.done.connect(lambda done: window.statusBar().showMessage(done.describe(), 15_000))
        task.signals.failed.connect(lambda exc: show_error(window, f"Exporting to {request.folder}", exc))
        self.session.jobs.start(task)
        return task

    def open_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self.editor, "Open a tracemap project", "",
                                              f"tracemap projects (*{SUFFIX});;all files (*)")
        if path:
            self.open(path)

    def _fill_recent(self, menu: QMenu) -> None:
        menu.clear()
        for path in recent_projects():
            menu.addAction(str(path), lambda p=path: self.open(p))
        if menu.isEmpty():
            menu.addAction("(none yet)").setEnabled(False)


class UndoMemoryDialog(ValueDialog):
    """The undo history's memory budget in MB (`values`: bytes)."""

    def __init__(self, budget: int, parent: QWidget | None = None):
        super().__init__("Undo memory", "undo-memory-dialog", parent)
        self.megabytes = QDoubleSpinBox(self)
        self.megabytes.setObjectName("undo-memory-mb")
        self.megabytes.setRange(0.0, 1e6)
        self.megabytes.setDecimals(0)
        self.megabytes.setSuffix(" MB")
        self.megabytes.setValue(budget / 2**20)
        self.megabytes.setToolTip("traces of the edits nearest the current state kept in memory; those of older "
                                  "edits are kept on disk and read back by undo and redo")
        self.add_row("Keep in memory", self.megabytes)

    def parse(self) -> int:
        return int(self.megabytes.value() * 2**20)


def undo_memory_setting() -> int:
    """Bytes of traces the undo history may keep in memory: the user setting "undo_memory_mb" (QSettings),
    else UNDO_MEMORY; a value that is no size is taken as unset."""
    try:
        mb = float(QSettings().value("undo_memory_mb", UNDO_MEMORY / 2**20))
    except (TypeError, ValueError):
        return UNDO_MEMORY
    return int(mb * 2**20) if math.isfinite(mb) and mb >= 0 else UNDO_MEMORY


def recent_projects() -> list[Path]:
    return [Path(p) for p in QSettings().value("recent", [], list) if Path(p).is_file()]


def remember(path: Path) -> None:
    path = path.resolve()
    QSettings().setValue("recent", [str(p) for p in [path, *(p for p in recent_projects() if p != path)][:RECENT]])


def check_display() -> None:
    """Refuse early, with a message, where Qt would abort the process for want of a display."""
    platform = os.environ.get("QT_QPA_PLATFORM", "")
    if (sys.platform.startswith("linux") and platform in ("", "xcb", "wayland")
            and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY")):
        raise TracemapError("no display to open windows on: run it in a desktop session, or set "
                            "QT_QPA_PLATFORM=offscreen for windows that are not shown")


def main(project: str | None = None, *, headless: bool = False) -> int:
    """Run the application on `project` (or none: File → Open); returns the exit status.

    headless : windows on the offscreen platform, built and closed at once (a smoke test of the set-up).
    """
    if headless:
        os.environ["QT_QPA_PLATFORM"] = "offscreen"
    else:
        check_display()
    app = QApplication.instance() or QApplication([sys.argv[0]])
    app.setOrganizationName("tracemap")
    app.setApplicationName("tracemap")
    install_excepthook()
    gui = Application()
    gui.show()
    if project is not None and not gui.open(project) and headless:
        return 2
    if headless:
        app.processEvents()
        gui.session.close()
        return 0
    return app.exec()
