"""The 3D viewer window (the paper's second module): the mesh, the 3D traces and the edits made on them.

It observes the session: any change of 3D traces or of the selection redraws the scene, whatever window
made it. Edits (terminations, deletions) go through undoable commands. The scene itself is built by
`engine.render`, the same code `tracemap render` uses headless.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
from matplotlib.path import Path as MplPath
from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtGui import QAction, QActionGroup, QKeySequence
from PySide6.QtWidgets import (QComboBox, QDialog, QDockWidget, QFileDialog, QLabel, QMainWindow, QMenu,
                               QTextBrowser, QToolBar, QWidget)

from engine.errors import TracemapError
from engine.mesh import Mesh
from engine.orientation import normal_to_dip_dipdir
from engine.register import Similarity, length_scale, rotate_directions
from engine.render import (COLOR_BY, DEFAULT_VIEW_ANGLE, TRACE_ACTORS, SceneStyle, add_scale_bar, add_surface,
                           add_traces, frame_view, look_from, place_legend)
from engine.scale_bar import ScaleBar, registered_scale_bar
from engine.topology import END_CODES, set_termination
from engine.traces import KINDS, TERMINATIONS, Trace3D
from tracemap_gui.analysis_menu import AnalysisMenu
from tracemap_gui.commands import EditTraces3D, ReplaceTraces3D, SetKind
from tracemap_gui.error_dialog import show_error
from tracemap_gui.facet_tool import FacetTool
from tracemap_gui.maps_panel import MapsPanel
from tracemap_gui.merge_tool import MergeTool
from tracemap_gui.orientation_tool import OrientationTool
from tracemap_gui.photo_drape import PhotoDrapePanel
from tracemap_gui.plots_panel import PlotsPanel
from tracemap_gui.scan_circle_tool import ScanCircleTool
from tracemap_gui.scanline_tool import ScanlineTool
from tracemap_gui.scene_view import SceneView, display_coordinates
from tracemap_gui.session import Session
from tracemap_gui.shortcuts import shortcut_rows, show_shortcuts
from tracemap_gui.termination_tool import TerminationTool
from tracemap_gui.workers import ProgressPanel, Task

TITLE = "tracemap: 3D viewer"
MOUSE_HELP = [("Rotate", "Left drag"), ("Pan", "Middle drag, or Shift + left drag"), ("Zoom", "Mouse wheel"),
              ("Select a trace", "Click"), ("Add to or remove from the selection", "Shift + click")]
PICK_PX = 6  # how near (display pixels) a click must fall to a trace: thin lines must be easy to hit
CATEGORICAL = tuple(c for c in COLOR_BY if c not in ("p21", "p32"))
TRACES_POLL_MS = 20  # after the mesh is read: how often to look whether the session has read the 3D traces
CAMERA_SAVE_MS = 800  # the camera is stored this long after it last moved


class Viewer3D(QMainWindow):
    """Mesh and 3D traces of the session's project; click a trace to select it (Shift adds)."""

    reveal2d = Signal(str, int)  # "show this 2D trace on its photo": image name, 2D trace id
    mesh_loaded = Signal(object)  # the Mesh, read after the project opened

    def __init__(self, session: Session, parent: QWidget | None = None, *, offscreen: bool | None = None):
        super().__init__(parent)
        self.setWindowTitle(TITLE)
        self.session = session
        self.mesh: Mesh | None = None
        self._arriving: Mesh | None = None  # read, its surface drawn; the traces follow in the next pass
        self._surface_of: tuple = ()  # the map and drape the surface was drawn with (`_surface_wanted`)
        self.style = SceneStyle(color_by=str(session.setting("viewer3d/color_by", "set")))
        self.view = SceneView(self, offscreen=offscreen)
        self.view.plotter.set_background("white")
        self.setCentralWidget(self.view)
        self._actors: dict[str, object] = {}
        self.click_handlers: list = []  # tools' f(x, y, additive) -> True when they took a click
        self._dock_groups: dict[str, QDockWidget] = {}  # the first dock of each group of tabbed panels
        self._build_actions()
        self._build_info_dock()
        self.statusBar().addPermanentWidget(ProgressPanel(session.jobs, self))
        self.maps_panel = MapsPanel(self)
        self.drape_panel = PhotoDrapePanel(self)
        self.plots_panel = PlotsPanel(session, self)
        self.addDockWidget(Qt.DockWidgetArea.BottomDockWidgetArea, self.plots_panel)
        self.view_menu.addAction(self.plots_panel.toggleViewAction())
        self.maps_panel.changed.connect(self._redraw)
        self.drape_panel.changed.connect(self._redraw)
        self.view.clicked.connect(self._pick)
        self.view.outlined.connect(self.select_inside)
        self.view.resized.connect(self._place_legend)
        # queued: in a pass of the event loop of its own, not in the one in which every window reloads
        session.opened.connect(self._load, Qt.ConnectionType.QueuedConnection)
        session.closed.connect(self._clear)
        # the view is stored once the camera rests, so a killed program reopens where it was
        self._camera_timer = QTimer(self, singleShot=True, interval=CAMERA_SAVE_MS)
        self._camera_timer.timeout.connect(self._store_camera)
        self.view.plotter.camera.AddObserver("ModifiedEvent", lambda *_: self._camera_timer.start())
        session.traces3d_changed.connect(self._redraw_traces)
        session.registration_changed.connect(self._show_info)
        session.registration_changed.connect(self._redraw_scale_bar)
        session.selection_changed.connect(self._redraw_traces)
        self.orientation_tool = OrientationTool(self)
        self.click_handlers.append(self.orientation_tool.handle_click)
        self.merge_tool = MergeTool(self)
        self.click_handlers.append(self.merge_tool.handle_click)
        self.facet_tool = FacetTool(self)
        self.click_handlers.append(self.facet_tool.handle_click)
        self.termination_tool = TerminationTool(self)
        self.click_handlers.append(self.termination_tool.handle_click)
        self.scanline_tool = ScanlineTool(self)
        self.click_handlers.append(self.scanline_tool.handle_click)
        self.scan_circle_tool = ScanCircleTool(self)
        self.click_handlers.append(self.scan_circle_tool.handle_click)
        self.analysis_menu = AnalysisMenu(self)
        tools = QActionGroup(self)  # one clicking tool at a time, or none
        tools.setExclusionPolicy(QActionGroup.ExclusionPolicy.ExclusiveOptional)
        for action in (self.box_action, self.lasso_action, self.orientation_tool.action, self.facet_tool.action,
                       self.termination_tool.action, self.scanline_tool.action, self.scan_circle_tool.action):
            tools.addAction(action)
        if session.is_open:
            self._load()

    # -- building -------------------------------------------------------------------------------------

    def _build_actions(self) -> None:
        bar = QToolBar("3D", self)
        bar.setObjectName("viewer3d-toolbar")
        self.addToolBar(bar)
        self.color_box = QComboBox(self)
        self.color_box.addItems(CATEGORICAL)
        self.color_box.setCurrentText(self.style.color_by if self.style.color_by in CATEGORICAL else "set")
        self.color_box.currentTextChanged.connect(self._set_color_by)
        bar.addWidget(QLabel(" Colour by ", self))
        bar.addWidget(self.color_box)
        self.reset_action = self._action("Reset view", "R", self._reset_view, bar)
        self.delete_action = self._action("Delete selected traces", QKeySequence.StandardKey.Delete,
                                          self._delete_selected, bar)
        self.reveal_action = self._action("Show on photo", "P", self._reveal, bar)
        self.box_action = self._select_mode_action("Box select", "S", "box", bar)
        self.lasso_action = self._select_mode_action("Lasso select", "L", "lasso", bar)
        self.screenshot_action = self._action("Save screenshot…", "Ctrl+Shift+S", self._save_screenshot, bar)
        menu = self.menuBar().addMenu("&Edit")
        menu.addAction(self.session.undo_stack.createUndoAction(self, "Undo"))
        menu.addAction(self.session.undo_stack.createRedoAction(self, "Redo"))
        menu.actions()[0].setShortcut(QKeySequence.StandardKey.Undo)
        menu.actions()[1].setShortcut(QKeySequence.StandardKey.Redo)
        menu.addAction(self.delete_action)
        self.termination_menu = self.menuBar().addMenu("&Termination")
        for end in ("start", "end"):
            sub = QMenu(f"Set {end} node", self)
            for code in TERMINATIONS:
                action = sub.addAction(f"{code} ({_TERMINATION_NAMES[code]})")
                action.triggered.connect(lambda _=False, e=end, c=code: self.set_termination(e, c))
            self.termination_menu.addMenu(sub)
        self.kind_menu = self.menuBar().addMenu("&Kind")
        for kind in KINDS:
            action = self.kind_menu.addAction(f"Make selected traces {kind}")
            action.setStatusTip("bedding bounds the fractures (an end on it abuts it) but is left out of their sets, "
                                "lengths, topology and intensities; the 2D traces take the kind too")
            action.triggered.connect(lambda _=False, k=kind: self.make_kind(k))
        view = self.view_menu = self.menuBar().addMenu("&View")
        view.addAction(self.reset_action)
        self.look_menu = view.addMenu("Look from photo")
        self.look_menu.aboutToShow.connect(self._list_photos)
        self.scale_bar: ScaleBar | None = None  # the one drawn
        self.scale_bar_action = QAction("Scale bar and north arrow", self, checkable=True)
        self.scale_bar_action.setStatusTip("a scale bar at the outcrop's foot and a north arrow, in the registered "
                                           "frame if there is one")
        self.scale_bar_action.toggled.connect(self._scale_bar_toggled)
        view.addAction(self.scale_bar_action)
        view.addAction(self.screenshot_action)
        self.tools_menu = self.menuBar().addMenu("&Tools")  # the clicking tools: the toolbar can overflow
        self.tools_menu.addActions([self.box_action, self.lasso_action])
        help_menu = self.menuBar().addMenu("&Help")
        self.shortcuts_action = help_menu.addAction("&Keyboard shortcuts")
        self.shortcuts_action.setShortcut(QKeySequence.StandardKey.HelpContents)
        self.shortcuts_action.triggered.connect(self.show_shortcuts)

    def add_tool(self, text: str, key: str, tip: str) -> QAction:
        """A clicking tool's checkable action, with its key, in this window, on its toolbar and in its Tools
        menu."""
        action = QAction(text, self)
        action.setCheckable(True)
        action.setShortcut(QKeySequence(key))
        action.setStatusTip(tip)
        self.addAction(action)
        self.findChild(QToolBar, "viewer3d-toolbar").addAction(action)
        self.tools_menu.addAction(action)
        return action

    def add_panel(self, widget: QWidget, title: str, name: str, *, group: str | None = None) -> QDockWidget:
        """Show a tool's panel in a dock of this window (on the right), listed in the View menu; the docks of
        one `group` share a place as tabs, the first one's raised."""
        dock = QDockWidget(title, self)
        dock.setObjectName(name)
        dock.setWidget(widget)
        first = self._dock_groups.setdefault(group, dock) if group is not None else dock
        if first is dock:
            self.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, dock)
        else:  # tabbed at once: a dock stacked below the others first would make the window as tall as them all
            self.tabifyDockWidget(first, dock)
            first.raise_()
        self.view_menu.addAction(dock.toggleViewAction())
        return dock

    def _select_mode_action(self, text: str, shortcut: str, mode: str, bar: QToolBar) -> QAction:
        action = self._action(text, shortcut, lambda: None, bar)
        action.setCheckable(True)
        # toggled, not triggered: also when another tool of the group turns it off
        action.toggled.connect(lambda on: self.view.set_select_mode(mode if on else None))
        action.setStatusTip(f"Drag a {mode} round traces to select them (Shift adds); turn off to rotate again")
        return action

    def _action(self, text: str, shortcut, slot, bar: QToolBar) -> QAction:
        action = QAction(text, self)
        action.setShortcut(QKeySequence(shortcut))
        action.triggered.connect(slot)
        bar.addAction(action)
        return action

    def _build_info_dock(self) -> None:
        self.info = QTextBrowser(self)
        self.info.setObjectName("trace-info")
        dock = QDockWidget("Selected trace", self)
        dock.setObjectName("trace-info-dock")
        dock.setWidget(self.info)
        self.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, dock)

    # -- loading and drawing --------------------------------------------------------------------------

    def _load(self) -> None:
        """Read the mesh in the background (millions of faces take seconds), then draw."""
        if not self.session.is_open:  # closed before this queued call came
            return
        project = self.session.project
        self.setWindowTitle(f"{TITLE}: {project.path.name}")
        try:
            path, origin = project.mesh_path, project.origin
        except TracemapError as exc:  # moved or deleted since the project was made
            self.statusBar().showMessage("no mesh: see the message", 10_000)
            show_error(self, "Loading the mesh", exc)
            return
        self.statusBar().showMessage("loading the mesh…")
        task = Task("Loading mesh", _read_mesh, path, origin)
        task.signals.done.connect(self._mesh_loaded)
        task.signals.failed.connect(lambda exc: show_error(self, "Loading the mesh", exc))
        self.session.jobs.start(task)

    def _mesh_loaded(self, mesh: Mesh) -> None:
        """Draw the surface now and the rest in the next pass of the event loop: together they held the GUI
        thread 0.1–0.15 s on a loaded machine. The mesh is the viewer's (`mesh`) once both are done."""
        saved = self.session.setting("viewer3d/camera")  # the camera first, then one frame of the mesh
        if saved:
            self.view.plotter.camera_position = [tuple(v) for v in saved]
            angle, *centre = self.session.setting("viewer3d/lens", [DEFAULT_VIEW_ANGLE, 0.0, 0.0])
            self.view.plotter.camera.view_angle = angle
            self.view.plotter.camera.SetWindowCenter(*centre)
        else:
            frame_view(self.view.plotter, mesh, np.array([c.centre for c in self.session.cameras().values()]))
        self._arriving = mesh
        self._draw_surface(mesh)
        QTimer.singleShot(0, self, self._mesh_arrived)

    def _mesh_arrived(self) -> None:
        if self.session.reading_traces3d:  # drawn once read, rather than waited for here
            QTimer.singleShot(TRACES_POLL_MS, self, self._mesh_arrived)
            return
        mesh, self._arriving = self._arriving, None
        if mesh is None:  # the project was closed meanwhile
            return
        self.mesh = mesh
        self.mesh_loaded.emit(mesh)  # a panel redrawing on it (a drape let go) redraws everything now
        self.scale_bar_action.setChecked(bool(self.session.setting("viewer3d/scale_bar", False)))
        self._draw_scale_bar()
        if any(a is not b for a, b in zip(self._surface_of, self._surface_wanted())):
            self._draw_surface(mesh)  # the map changed in between
        self._redraw_traces()
        self.statusBar().showMessage(f"{len(mesh.faces):,} faces, {len(self.session.traces3d())} traces", 5000)

    def _clear(self) -> None:
        self.setWindowTitle(TITLE)
        self.mesh = self._arriving = None
        self.view.plotter.clear()
        self.view.refresh()

    def _redraw(self) -> None:
        """Draw everything again: the mesh (with its map or drape) and the traces."""
        if self.mesh is None:
            return
        self._draw_surface(self.mesh)
        self._redraw_traces()

    def _draw_surface(self, mesh: Mesh) -> None:
        """The mesh with the maps panel's map or the draped photo (the traces' actors stay)."""
        self._surface_of = self._surface_wanted()
        self.style.map_name, self.style.clim = self.maps_panel.map_name, self.maps_panel.clim
        traces = {name: self._actors[name] for name in TRACE_ACTORS if name in self._actors}
        self._actors = add_surface(self.view.plotter, mesh, self.style, vertex_map=self.maps_panel.values,
                                   drape=self.drape_panel.drape) | traces
        self._actors["mesh"].SetPickable(False)

    def _surface_wanted(self) -> tuple:
        return self.maps_panel.map_name, self.maps_panel.clim, self.maps_panel.values, self.drape_panel.drape

    def _redraw_traces(self) -> None:
        """Draw the traces again (an edit, the selection, the colouring): the mesh of millions of faces stays."""
        if self.mesh is None:
            return
        self.style.selected = set(self.session.selected3d)
        for name in TRACE_ACTORS:
            self._actors.pop(name, None)
        self._actors.update(add_traces(self.view.plotter, self.session.traces3d(), self.style))
        # depth range of what is now drawn: a camera set before the mesh was added (on loading) kept the empty
        # scene's 0.01–1000, which blurs depth and makes picks return traces in front of the clicked one
        self.view.plotter.renderer.ResetCameraClippingRange()
        self._show_info()
        self.view.refresh()

    def _place_legend(self, width: int, height: int) -> None:
        place_legend(self.view.plotter, (width, height))
        self.view.refresh()

    def _scale_bar_toggled(self, shown: bool) -> None:
        if self.session.is_open:
            self.session.set_setting("viewer3d/scale_bar", shown)
        self._redraw_scale_bar()

    def _redraw_scale_bar(self) -> None:
        self._draw_scale_bar()
        self.view.refresh()

    def _draw_scale_bar(self) -> None:
        """The scale bar (`scale_bar`) in front of where the photos were taken, or none (unchecked, no mesh)."""
        self.scale_bar = None
        if self.mesh is not None and self.scale_bar_action.isChecked():
            centres = np.array([c.centre for c in self.session.cameras().values()])
            self.scale_bar = registered_scale_bar(self.mesh, centres.mean(axis=0), self.session.similarity())
        add_scale_bar(self.view.plotter, self.scale_bar)

    def _list_photos(self) -> None:
        self.look_menu.clear()
        for name in sorted(self.session.cameras()):
            self.look_menu.addAction(name, lambda n=name: self.look_from(n))

    def look_from(self, name: str) -> None:
        """See the mesh as photo `name` does (its height fills the view; `engine.render.look_from`)."""
        if self.mesh is None:
            self.statusBar().showMessage("the mesh is still loading: look from the photo once it is shown", 5000)
            return
        look_from(self.view.plotter, self.session.cameras()[name], self.mesh)
        self.view.refresh()

    def _reset_view(self) -> None:
        if self.mesh is None:
            return
        centres = np.array([c.centre for c in self.session.cameras().values()])
        frame_view(self.view.plotter, self.mesh, centres)
        self.view.refresh()

    def _set_color_by(self, color_by: str) -> None:
        self.style.color_by = color_by
        self.session.set_setting("viewer3d/color_by", color_by)
        self._redraw_traces()

    # -- picking and editing --------------------------------------------------------------------------

    def pick_trace(self, x: int, y: int) -> int | None:
        """Id of the trace drawn nearest display position (x, y) (origin bottom-left), within PICK_PX, or None.

        Nearest on the screen, not nearest the camera (as a cell picker with a tolerance would take): where
        traces cross or run side by side, the one under the cursor wins.
        """
        traces = self.session.traces3d()
        if self.mesh is None or not traces:
            return None
        shown = display_coordinates(self.view.plotter.renderer, np.vstack([t.points for t in traces]))
        owner = np.repeat(np.arange(len(traces)), [len(t.points) for t in traces])
        joined = owner[:-1] == owner[1:]
        distance = _segment_distance(np.array([x, y], dtype=float), shown[:-1][joined], shown[1:][joined])
        if not np.isfinite(distance).any():
            return None
        k = int(np.nanargmin(distance))
        return traces[owner[:-1][joined][k]].id if distance[k] <= PICK_PX else None

    def _pick(self, x: int, y: int, additive: bool) -> None:
        if any(handler(x, y, additive) for handler in self.click_handlers):
            return  # an active tool took the click
        picked = self.pick_trace(x, y)
        current = set(self.session.selected3d)
        if picked is None:
            self.session.select3d(current if additive else ())
        elif additive:
            self.session.select3d(current ^ {picked})
        else:
            self.session.select3d({picked})

    def select_inside(self, outline: np.ndarray, additive: bool = False) -> None:
        """Select the traces with a vertex drawn inside the outline, a polygon (N, 2) of display coordinates
        (origin bottom-left), as the box and lasso tools draw it."""
        traces = self.session.traces3d()
        if not traces:
            return
        shown = display_coordinates(self.view.plotter.renderer, np.vstack([t.points for t in traces]))
        inside = MplPath(outline).contains_points(np.nan_to_num(shown, nan=-1e9))
        owner = np.repeat(np.arange(len(traces)), [len(t.points) for t in traces])
        picked = {traces[i].id for i in np.unique(owner[inside])}
        self.session.select3d(picked | set(self.session.selected3d) if additive else picked)

    def shortcuts(self) -> list[tuple[str, str]]:
        """(what, keys) for every action with a shortcut, then the mouse gestures."""
        return shortcut_rows(self, MOUSE_HELP)

    def show_shortcuts(self) -> QDialog:
        return show_shortcuts(self, self.shortcuts())

    def selected_traces(self) -> list[Trace3D]:
        ids = self.session.selected3d
        return [t for t in self.session.traces3d() if t.id in ids]

    def set_termination(self, end: str, code: str) -> None:
        traces = self.selected_traces()
        if not traces:
            self.statusBar().showMessage("select a trace first", 3000)
            return
        self.push(EditTraces3D(self.session, traces, [_set_by_hand(t, end, code) for t in traces],
                                f"Set {end} node to {code}"))

    def make_kind(self, kind: str) -> None:
        """Make the selected 3D traces `kind`, with the 2D traces they were made from: one undoable edit."""
        if not self.session.selected3d:
            self.statusBar().showMessage("select a trace first", 3000)
            return
        command = SetKind(self.session, kind, ids3d=self.session.selected3d)
        if not command.changed:
            self.statusBar().showMessage(f"the selected traces are {kind} already", 3000)
            return
        self.push(command)

    def _delete_selected(self) -> None:
        traces = self.selected_traces()
        if traces:
            self.push(ReplaceTraces3D(self.session, traces, [], f"Delete {len(traces)} 3D traces"))

    def push(self, command) -> None:
        """Apply an edit (one undoable command); a failure is shown and nothing is stored."""
        try:
            self.session.push(command)
        except Exception as exc:  # noqa: BLE001 - shown to the user, nothing was stored
            show_error(self, command.text(), exc)

    def _reveal(self) -> None:
        traces = self.selected_traces()
        if traces and (source := self._source(traces[0])) is not None:
            self.reveal2d.emit(*source)

    def _source(self, trace: Trace3D) -> tuple[str, int] | None:
        """The photo and 2D trace that gave most of a 3D trace's vertices: a merged trace has parents on
        several photos, listed by id, not by photo."""
        counts = np.bincount(trace.image_index, minlength=len(trace.images))
        parents = set(trace.parents)
        for k in np.argsort(-counts, kind="stable"):
            image = trace.images[k]
            parent = next((t.id for t in self.session.traces2d(image) if t.id in parents), None)
            if parent is not None:
                return image, parent
        return None

    def _save_screenshot(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save screenshot", "tracemap-3d.png", "Images (*.png *.jpg)")
        if path:
            try:
                self.view.save_frame(path)
            except Exception as exc:  # noqa: BLE001 - shown to the user
                show_error(self, "Saving the screenshot", exc)
                return
            self.statusBar().showMessage(f"saved {path}", 5000)

    def _show_info(self) -> None:
        traces = self.selected_traces()
        self.info.setHtml("" if len(traces) != 1 else _describe(traces[0], self.session.similarity()))

    def _store_camera(self) -> None:
        if self.session.is_open and self.mesh is not None:
            camera = self.view.plotter.camera
            self.session.set_setting("viewer3d/camera", [list(v) for v in self.view.plotter.camera_position])
            self.session.set_setting("viewer3d/lens", [camera.view_angle, *camera.GetWindowCenter()])

    def closeEvent(self, event) -> None:
        self._camera_timer.stop()
        self._store_camera()
        super().closeEvent(event)


_TERMINATION_NAMES = {"B": "blind", "T": "abutting", "X": "crossing", "C": "censored"}


def _set_by_hand(trace: Trace3D, end: str, code: str) -> Trace3D:
    """A copy of `trace` with the termination of one end set by hand. B, T and C are marked as such
    (`engine.topology.set_termination`), so Analyse keeps them; X, a crossing, is the analysis's to find."""
    edited = replace(trace, extra=copy.deepcopy(trace.extra))  # the command keeps `trace` for undo
    if code in END_CODES:
        set_termination(edited, end, code)
    else:
        setattr(edited, "term_start" if end == "start" else "term_end", code)
    return edited


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from point p (2,) to each segment a–b (N, 2); NaN where an end is behind the camera."""
    d = b - a
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
    t = np.where(np.isfinite(t), t, 0.0)  # a zero-length segment: its end point
    return np.linalg.norm(a + t[:, None] * d - p, axis=1)


def _read_mesh(path, origin, *, progress) -> Mesh:
    from engine.mesh import read_mesh

    progress(0.0, "reading the mesh")
    mesh = read_mesh(path, origin=origin)
    mesh.mean_edge_length  # cached here, off the GUI thread: the maps panel wants it (0.5 s at 3M faces)
    return mesh


def _describe(t: Trace3D, similarity: Similarity | None = None) -> str:
    """The selected trace's readout; lengths and orientation in the registered frame when there is one."""
    scale = length_scale(similarity)
    rows = [("trace", t.id), ("kind", t.kind), ("vertices", len(t.points)), ("surface length", f"{scale * t.surface_length:.3f} m"),
            ("chord length", f"{scale * t.chord_length:.3f} m"),
            ("terminations", f"{t.term_start or '–'} / {t.term_end or '–'}"), ("set", t.set_id),
            ("component", t.component), ("photos", ", ".join(t.images)),
            ("2D traces", ", ".join(map(str, t.parents)))]
    if t.normal is not None:
        dip, dipdir = normal_to_dip_dipdir(rotate_directions(t.normal, similarity))
        rows += [("dip / dip direction", f"{float(dip):.1f}° / {float(dipdir):05.1f}°"),
                 ("method", t.method), ("K, M", f"{t.K:.2f}, {t.M:.2f}")]
    if similarity is not None:
        rows.append(("frame", "the GCPs' (registered)"))
    return "<table>" + "".join(f"<tr><td><b>{k}</b></td><td>{v}</td></tr>" for k, v in rows) + "</table>"
