"""The 2D image editor: the project's photos, the photo view with its trace layers, tools, auto-trace, 2D → 3D.

Everything the user changes goes through the session as an undoable command and is in the project file
at once; what the user looks at (photo, zoom, tool, colouring) is stored as project settings, so reopening
the project shows the same thing.
"""

from __future__ import annotations

from pathlib import Path

from PySide6.QtCore import QPointF, Qt, QTimer, Signal
from PySide6.QtGui import QAction, QActionGroup, QKeySequence
from PySide6.QtWidgets import QComboBox, QDialog, QDockWidget, QFileDialog, QLabel, QMainWindow, QWidget

from engine.errors import TracemapError
from engine.extract import Extraction
from engine.io import read_traces_csv
from engine.traces import KINDS, Trace2D
from tracemap_gui import commands, tools
from tracemap_gui.autotrace_panel import AutotracePanel
from tracemap_gui.error_dialog import show_error
from tracemap_gui.extraction import Extractor, extraction_command
from tracemap_gui.gcp_tool import GcpPanel, GcpTool
from tracemap_gui.photo_list import PhotoList
from tracemap_gui.photo_view import ZOOM_STEP, PhotoView
from tracemap_gui.session import Session
from tracemap_gui.shortcuts import shortcut_rows, show_shortcuts
from tracemap_gui.trace_layer import PlacedLayer, ProposalLayer, StageOverlay, TraceLayer
from tracemap_gui.workers import ProgressPanel, Task

SAVE_VIEW_DELAY_MS = 300  # store the zoom this long after the view last moved
MOUSE_HELP = [("Zoom about the cursor", "Mouse wheel"), ("Pan", "Middle button drag, or Space + left drag"),
              ("Finish a line", "Double-click or Enter"), ("Take back the last vertex", "Backspace"),
              ("Cancel the gesture / clear the selection", "Esc"), ("Add to the selection", "Shift + click")]


TITLE = "tracemap: image editor"
NO_PROJECT = "no project open: File → New project… (Ctrl+N) makes one from a mesh and cameras; Open project… (Ctrl+O)"


class ImageEditor(QMainWindow):
    """The image editor window over a session (which may have no project open yet). `look3d(image)` asks
    the 3D viewer to look from the photo shown."""

    look3d = Signal(str)

    def __init__(self, session: Session, parent: QWidget | None = None):
        super().__init__(parent)
        self.setObjectName("image-editor")
        self.setWindowTitle(TITLE)
        self.session = session
        self.view = PhotoView()
        self.setCentralWidget(self.view)
        scene = self.view.scene()
        self.traces = TraceLayer(session, scene)
        self.placed = PlacedLayer(session, scene)
        self.proposals = ProposalLayer(scene)
        self.overlay = StageOverlay(scene)
        self.photos = PhotoList(session)
        self.autotrace = AutotracePanel(session, self.view, self.proposals, self.overlay, self)
        self.gcps = GcpPanel(session, self)
        self.tools = self._make_tools()
        self._extractor = Extractor(session.mesh_tracer)
        self._extracting: Task | None = None
        self._save_view = QTimer(self, singleShot=True, interval=SAVE_VIEW_DELAY_MS)
        self._save_view.timeout.connect(self._store_view)
        self._build_docks()
        self._build_actions()
        self._build_status()
        self._connect()
        self.resize(1280, 860)
        if session.is_open:
            self._project_opened()
        else:
            self.set_tool("Select")
            self.hint.setText(NO_PROJECT)  # after the tool's own hint: an empty window says how to begin

    # -- construction ---------------------------------------------------------------------------------

    def _make_tools(self) -> dict[str, tools.Tool]:
        kinds = (tools.DrawPolyline, tools.GuidedCurve, tools.SplineCurve, tools.EditVertices, tools.Split,
                 tools.Join, tools.Erase)
        made = [tools.Select(self.session, self.view, self.proposals), *(k(self.session, self.view) for k in kinds),
                GcpTool(self.session, self.view, self.gcps)]
        return {tool.name: tool for tool in made}

    def _build_docks(self) -> None:
        dock = QDockWidget("Photos", self)
        dock.setObjectName("photos-dock")
        dock.setWidget(self.photos)
        self.addDockWidget(Qt.DockWidgetArea.LeftDockWidgetArea, dock)
        self.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, self.autotrace)
        self.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, self.gcps)
        self.resizeDocks([dock], [170], Qt.Orientation.Horizontal)
        self._docks = [dock, self.autotrace, self.gcps]

    def _action(self, text: str, slot, shortcut: str | QKeySequence.StandardKey | None = None, *,
                checkable: bool = False, tip: str = "") -> QAction:
        action = QAction(text, self)
        if shortcut is not None:
            action.setShortcut(QKeySequence(shortcut))
        action.setCheckable(checkable)
        action.setStatusTip(tip)
        action.triggered.connect(slot)
        self.addAction(action)  # shortcuts work wherever the focus is in this window
        return action

    def _build_actions(self) -> None:
        bar = self.menuBar()
        self.file_menu = bar.addMenu("&File")  # the application adds Open, Recent and Quit
        undo = self.session.undo_stack.createUndoAction(self, "&Undo")
        undo.setShortcut(QKeySequence.StandardKey.Undo)
        redo = self.session.undo_stack.createRedoAction(self, "&Redo")
        redo.setShortcuts([QKeySequence("Ctrl+Shift+Z"), QKeySequence("Ctrl+Y")])
        self.addActions([undo, redo])
        for action in (undo, redo):  # after the stack's own slot: the tool sees the project as undone
            action.triggered.connect(self._undone)
        edit = bar.addMenu("&Edit")
        edit.addActions([undo, redo])
        edit.addSeparator()
        edit.addAction(self._action("&Delete", self._delete, QKeySequence.StandardKey.Delete,
                                    tip="erase the selected traces, or the highlighted vertex"))
        edit.addAction(self._action("Select &all", self._select_all, QKeySequence.StandardKey.SelectAll))

        view = bar.addMenu("&View")
        view.addAction(self._action("&Fit photo", self.view.fit, "F"))
        view.addAction(self._action("Zoom &in", lambda: self.view.zoom(ZOOM_STEP), "+"))
        view.addAction(self._action("Zoom &out", lambda: self.view.zoom(1 / ZOOM_STEP), "-"))
        view.addAction(self._action("&Actual pixels", lambda: self.view.zoom(1 / self.view.scale_factor), "1"))
        view.addSeparator()
        self.colour_action = self._action("Colour by 2D &component", self._colour_by_component, "C",
                                          checkable=True, tip="colour traces by connected component")
        self.set_colour_action = self._action("Colour by 3D &set", self._colour_by_set, "Shift+C",
                                              checkable=True, tip="colour traces by the set of the 3D trace "
                                                                  "each became (grey: none yet)")
        self.kind_colour_action = self._action("Colour by &kind", self._colour_by_kind, "Shift+K", checkable=True,
                                               tip="colour traces by kind (every colouring draws bedding dashed, "
                                                   "veins dotted, faults dash-dotted)")
        colouring = QActionGroup(self)  # one colouring at a time, or by source
        colouring.setExclusionPolicy(QActionGroup.ExclusionPolicy.ExclusiveOptional)
        for action in (self.colour_action, self.set_colour_action, self.kind_colour_action):
            colouring.addAction(action)
            view.addAction(action)
        self.placed_action = self._action("Show p&laced pixels", self._show_placed, "L", checkable=True,
                                          tip="a white core along the trace pixels placed on the mesh; gaps were "
                                              "left off it (missed, on an occluding edge, slivers)")
        view.addAction(self.placed_action)
        view.addAction(self._action("&Next photo", lambda: self._step_photo(1), "PgDown"))
        view.addAction(self._action("&Previous photo", lambda: self._step_photo(-1), "PgUp"))
        self.look3d_action = self._action("Look from this photo in &3D", self._look3d, "3",
                                          tip="the 3D viewer sees the mesh as this photo does")
        view.addAction(self.look3d_action)
        view.addSeparator()
        for dock in self._docks:
            view.addAction(dock.toggleViewAction())

        self.tool_actions: dict[str, QAction] = {}
        group = QActionGroup(self)
        tool_menu = bar.addMenu("&Tools")
        toolbar = self.addToolBar("Tools")
        toolbar.setObjectName("tools-toolbar")
        shortcuts = {"GCP": "K", "Select": "S", "Draw polyline": "D", "Guided curve": "G", "Spline curve": "B",
                     "Edit vertices": "V", "Split": "X", "Join": "J", "Erase": "E"}
        for name, tool in self.tools.items():
            action = self._action(name, lambda _=False, n=name: self.set_tool(n), shortcuts[name], checkable=True,
                                  tip=tool.hint)
            group.addAction(action)
            tool_menu.addAction(action)
            toolbar.addAction(action)
            self.tool_actions[name] = action
        toolbar.addSeparator()
        self.kind_box = QComboBox(self)
        self.kind_box.addItems(KINDS)
        self.kind_box.setToolTip("what the traces drawn next are: bedding bounds the fractures but is left out of "
                                 "their sets, lengths, topology and intensities")
        self.kind_box.currentTextChanged.connect(self._choose_kind)
        toolbar.addWidget(QLabel(" New traces are ", self))
        toolbar.addWidget(self.kind_box)
        toolbar.addSeparator()
        toolbar.addActions([undo, redo])

        traces = bar.addMenu("T&races")
        self.extract_actions = [
            self._action("&Extract this photo to 3D", lambda: self.extract(all_photos=False), "Ctrl+E"),
            self._action("Extract &all photos to 3D", lambda: self.extract(all_photos=True), "Ctrl+Shift+E")]
        traces.addAction(self._action("&Import traces from CSV…", self.ask_import,
                                      tip="2D traces from a CSV of columns image,trace,u,v (as tracemap import-traces)"))
        self.kind_menu = traces.addMenu("Make selected traces")
        for kind in KINDS:
            self.kind_menu.addAction(self._action(kind, lambda _=False, k=kind: self.make_kind(k),
                                                  tip=f"make the selected traces {kind}, with the 3D traces made "
                                                      "from them"))
        traces.addSeparator()
        traces.addActions(self.extract_actions)
        traces.addAction(self._action("Auto-trace the &view", lambda: self.autotrace.run(whole=False), "Ctrl+R"))
        traces.addAction(self._action("Auto-trace the &photo", lambda: self.autotrace.run(whole=True),
                                      "Ctrl+Shift+R"))
        toolbar.addSeparator()
        toolbar.addActions(self.extract_actions)

        help_menu = bar.addMenu("&Help")
        help_menu.addAction(self._action("&Keyboard shortcuts", self.show_shortcuts,
                                         QKeySequence.StandardKey.HelpContents))

    def ask_import(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Import 2D traces", "", "CSV files (*.csv);;all files (*)")
        if path:
            self.import_traces(path)

    def import_traces(self, path: str | Path) -> int:
        """Add the 2D traces of a CSV (columns image,trace,u,v; `engine.io.read_traces_csv`) as one undoable
        edit; how many were added (0 when the file is refused: a dialog names the line and column)."""
        if not self.session.is_open:
            self.statusBar().showMessage("open a project first", 5000)
            return 0
        try:
            traces = read_traces_csv(path, self.session.cameras())
            self.session.push(commands.AddTraces2D(self.session, traces, f"Import {len(traces)} traces"))
        except TracemapError as exc:
            show_error(self, f"Importing {path}", exc)
            return 0
        photos = len({t.image for t in traces})
        self.statusBar().showMessage(f"imported {len(traces)} traces on {photos} photos from {path}", 10_000)
        return len(traces)

    def _build_status(self) -> None:
        self.hint = QLabel()
        self.where = QLabel()
        self.zoom_label = QLabel()
        self.progress = ProgressPanel(self.session.jobs)
        status = self.statusBar()
        status.addWidget(self.hint, 1)
        status.addPermanentWidget(self.where)
        status.addPermanentWidget(self.zoom_label)
        status.addPermanentWidget(self.progress)

    def _project_closed(self) -> None:
        self.setWindowTitle(TITLE)
        self.show_photo(None)
        self.hint.setText(NO_PROJECT)

    def _edit_failed(self, message: str) -> None:
        show_error(self, "Storing the edit", message)

    def _connect(self) -> None:
        session = self.session
        session.opened.connect(self._project_opened)
        # bound methods, not lambdas: Qt drops them if this window is deleted before the session closes
        session.closed.connect(self._project_closed)
        session.failed.connect(self._edit_failed)
        session.kind_changed.connect(self.kind_box.setCurrentText)
        self.photos.chosen.connect(self.show_photo)
        self.view.photo_failed.connect(lambda image, exc: show_error(self, f"Showing photo {image}", exc))
        self.view.hint.connect(self.hint.setText)
        self.view.cursor_moved.connect(self._show_cursor)
        self.view.view_changed.connect(self._view_changed)

    # -- photos ---------------------------------------------------------------------------------------

    def _project_opened(self) -> None:
        self.hint.setText("")
        names = self.session.images()
        last = self.session.setting("editor.photo")
        self.traces.set_colour_by(self.session.setting("editor.colour_by", "source"))
        self.colour_action.setChecked(self.traces.colour_by == "component")
        self.set_colour_action.setChecked(self.traces.colour_by == "set")
        self.kind_colour_action.setChecked(self.traces.colour_by == "kind")
        self.kind_box.setCurrentText(self.session.kind)
        self.placed_action.setChecked(bool(self.session.setting("editor.show_placed", True)))
        self.placed.set_visible(self.placed_action.isChecked())
        self.set_tool(self.session.setting("editor.tool", "Select"))
        self.show_photo(last if last in names else (names[0] if names else None))
        self.setWindowTitle(f"{TITLE}: {self.session.path.name}")

    def show_photo(self, image: str | None) -> None:
        """Show a photo with its traces, at the zoom it had when last shown."""
        if self.view.tool is not None:
            self.view.tool.cancel()
        self.autotrace.photo_changed()
        self.session.select2d([])
        if image is None:
            self.view.show_photo(None)
            self.traces.show(None)
            self.placed.show(None)
            return
        camera = self.session.camera(image)
        try:
            path = self.session.project.image_path(image)
        except TracemapError as exc:  # moved or changed: show the traces on a blank photo, say why
            show_error(self, f"Showing photo {image}", exc)
            path = None
        self.view.show_photo(image, (camera.width, camera.height), path)
        self.traces.show(image, (camera.width, camera.height))
        self.placed.show(image)
        state = self.session.setting("editor.views", {}).get(image)
        if state:
            self.view.restore_view_state(state)
        self.photos.set_current(image)
        self.session.set_setting("editor.photo", image)
        self._view_changed()

    def reveal(self, image: str, trace_id: int) -> None:
        """Show a 2D trace: its photo, centred on it, selected (the 3D viewer's "Show on photo")."""
        if image != self.view.image:
            self.show_photo(image)
        trace = next((t for t in self.session.traces2d(image) if t.id == trace_id), None)
        if trace is not None:
            self.view.centerOn(*trace.polyline[len(trace.polyline) // 2])
            self.session.select2d([trace_id])
        self.show()
        self.raise_()

    def _look3d(self) -> None:
        if self.view.image is not None:
            self.look3d.emit(self.view.image)

    def _step_photo(self, step: int) -> None:
        names = self.photos.names()
        if self.view.image in names:
            self.show_photo(names[(names.index(self.view.image) + step) % len(names)])

    def _view_changed(self) -> None:
        self.zoom_label.setText(f"{self.view.scale_factor:.0%}")
        if self.view.image is not None:
            self._save_view.start()

    def _store_view(self) -> None:
        if self.view.image is None or not self.session.is_open:
            return
        views = self.session.setting("editor.views", {})
        views[self.view.image] = self.view.view_state()
        self.session.set_setting("editor.views", views)

    def _show_cursor(self, pos: QPointF) -> None:
        self.where.setText(f"u {pos.x():.1f}  v {pos.y():.1f} px")

    # -- tools and display ----------------------------------------------------------------------------

    def _undone(self) -> None:
        if self.view.tool is not None:
            self.view.tool.undone()

    def set_tool(self, name: str) -> None:
        if name not in self.tools:
            name = "Select"
        self.tool_actions[name].setChecked(True)
        self.view.set_tool(self.tools[name])
        self.session.set_setting("editor.tool", name)

    def _colour_by_component(self, on: bool) -> None:
        self._colour_by("component" if on else "source")

    def _colour_by_set(self, on: bool) -> None:
        self._colour_by("set" if on else "source")

    def _colour_by_kind(self, on: bool) -> None:
        self._colour_by("kind" if on else "source")

    def _choose_kind(self, kind: str) -> None:
        if self.session.is_open and kind != self.session.kind:
            self.session.set_kind(kind)

    def make_kind(self, kind: str) -> None:
        """Make the selected 2D traces `kind` (and the 3D traces made from them), one undoable edit."""
        if not self.session.is_open or not self.session.selected2d:
            self.statusBar().showMessage("select traces first", 3000)
            return
        command = commands.SetKind(self.session, kind, ids2d=self.session.selected2d)
        if not command.changed:
            self.statusBar().showMessage(f"the selected traces are {kind} already", 3000)
            return
        self.session.push(command)
        self.statusBar().showMessage(command.text(), 5000)

    def _colour_by(self, mode: str) -> None:
        self.traces.set_colour_by(mode)
        self.session.set_setting("editor.colour_by", mode)

    def _show_placed(self, on: bool) -> None:
        self.placed.set_visible(on)
        self.session.set_setting("editor.show_placed", on)

    def _delete(self) -> None:
        if self.view.tool is not None and self.view.image is not None:
            self.view.tool.delete()

    def _select_all(self) -> None:
        if self.view.image is not None:
            self.session.select2d(t.id for t in self.session.traces2d(self.view.image))

    # -- 2D → 3D --------------------------------------------------------------------------------------

    def extract(self, all_photos: bool) -> None:
        """Ray-trace the 2D traces of this photo (or all photos) onto the mesh, on a worker."""
        if self._extracting is not None or not self.session.is_open:
            return
        images = self.session.images() if all_photos else [self.view.image] if self.view.image else []
        traces = [t for image in images for t in self.session.traces2d(image)]
        if not traces:
            self.hint.setText("no 2D traces to extract")
            return
        try:
            mesh_path = self.session.project.mesh_path
        except TracemapError as exc:
            show_error(self, "Extraction", exc)
            return
        cameras = {image: self.session.camera(image) for image in images}
        task = Task("Extracting 3D traces", self._extractor, traces, cameras, mesh_path, self.session.project.origin)
        task.signals.done.connect(lambda result: self._extracted(traces, result))
        task.signals.failed.connect(lambda exc: show_error(self, "Extraction", exc))
        task.signals.cancelled.connect(lambda: self.hint.setText("extraction cancelled; nothing was changed"))
        task.signals.ended.connect(self._extraction_ended)
        for action in self.extract_actions:
            action.setEnabled(False)
        self._extracting = self.session.jobs.start(task)

    def _extracted(self, parents: list[Trace2D], result: Extraction) -> None:
        self.session.push_in_background(extraction_command(self.session, parents, result))
        self.hint.setText(f"extracted {len(result.traces)} 3D traces from {len(parents)} 2D traces "
                          f"({result.n_rays:,} rays, {result.n_missed:,} missed the mesh, "
                          f"{result.n_edge:,} on occluding edges)")

    def _extraction_ended(self) -> None:
        self._extracting = None
        for action in self.extract_actions:
            action.setEnabled(True)

    # -- help -----------------------------------------------------------------------------------------

    def shortcuts(self) -> list[tuple[str, str]]:
        """(what, keys) for every action with a shortcut, then the mouse gestures."""
        return shortcut_rows(self, MOUSE_HELP)

    def show_shortcuts(self) -> QDialog:
        return show_shortcuts(self, self.shortcuts())
