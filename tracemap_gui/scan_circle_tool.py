"""The 3D viewer's Scan circle tool: Mauldon's circular windows laid on the outcrop, read as P21, P20 and mean
trace length.

With the tool on, a click on the mesh lays a window of the rock within the radius of the point picked; it is
measured on a worker (`engine.scan_circle.measure_scan_circle`: the traces crossing its edge, their ends
inside it, the cut ends and unseen rock that bias it) and stored as one undoable edit. Lay grid covers the
face with touching windows, whole on the rock (`engine.scan_circle.grid_scan_circles`), as one edit. Stored
windows are listed with their readouts (in the registered frame, if any) and pooled, and drawn as their edge
on the rock with a mark at every crossing and end; they are measured again when the traces change (reusing
each window's rock) and exported by `tracemap export` (scan_circles.csv, summary.json).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from PySide6.QtCore import Signal
from PySide6.QtWidgets import QFormLayout, QHBoxLayout, QLabel, QLineEdit, QPushButton, QVBoxLayout, QWidget

from engine.errors import Progress, TracemapError
from engine.register import length_scale
from engine.render import add_scan_circles
from engine.scan_circle import (ScanCircle, WindowMeasure, counts_report, describe_pooled_windows, describe_window,
                                grid_scan_circles, measure_scan_circle, pooled_windows, window_report)
from tracemap_gui.commands import SCAN_CIRCLES
from tracemap_gui.error_dialog import describe, show_error
from tracemap_gui.length_box import length_box
from tracemap_gui.sample_tool import SampleTool
from tracemap_gui.workers import Task, pick_mesh

if TYPE_CHECKING:
    from engine.mesh import Mesh
    from engine.sight import Sight
    from engine.traces import Trace3D
    from tracemap_gui.viewer3d import Viewer3D

RADIUS_SETTING = "scan_circle/radius"
DEFAULT_RADIUS = 2.0  # m: Rohrbaugh et al. (2002) size windows to hold some tens of crossings


class ScanCircleTool(SampleTool):
    """Lay, list, read and remove scan circles in one 3D viewer (a dock and a checkable tool action)."""

    laid = Signal(object)  # the WindowMeasures just stored, or None when none could be laid
    noun = "scan circle"
    storage = SCAN_CIRCLES

    def __init__(self, viewer: Viewer3D):
        super().__init__(viewer)
        self._laying: dict[Task, str] = {}  # picks ("") and measurings of new windows (their edit's text)
        self.action = viewer.add_tool("Scan circle", "C", "Click a point on the rock to lay a circular scan window "
                                                          "round it")
        self.action.toggled.connect(self._toggled)
        self._build_dock()
        self.watch()

    def _build_dock(self) -> None:
        panel = QWidget()
        self.message = QLabel("Turn on the Scan circle tool (C) and click the rock", panel)
        self.message.setObjectName("scan-circle-message")
        self.message.setWordWrap(True)
        self.radius = length_box(panel, "scan-circle-radius", "radius of a new window (and of the grid's)", low=0.01,
                                 high=1000.0, decimals=2, step=0.5)
        self.radius.valueChanged.connect(lambda value: self.session.set_setting(RADIUS_SETTING, value))
        self.name = QLineEdit(panel)
        self.name.setObjectName("scan-circle-name")
        self.name.setPlaceholderText("optional, e.g. bench 2")
        self.grid_button = QPushButton("Lay grid", panel)
        self.grid_button.setObjectName("scan-circle-grid")
        self.grid_button.setToolTip("cover the outcrop's face with touching windows of this radius, each whole on "
                                    "the rock (`tracemap scan-circle --grid`)")
        self.grid_button.clicked.connect(self.lay_grid)
        self.build_list(panel)
        form = QFormLayout()
        form.addRow("Radius", self.radius)
        form.addRow("Name", self.name)
        layout = QVBoxLayout(panel)
        layout.addWidget(self.message)
        layout.addLayout(form)
        layout.addWidget(QLabel("Stored scan circles", panel))
        layout.addWidget(self.list)
        layout.addWidget(self.details)
        buttons = QHBoxLayout()
        buttons.addWidget(self.grid_button)
        buttons.addWidget(self.remove_button)
        layout.addLayout(buttons)
        self.dock = self.viewer.add_panel(panel, "Scan circles", "scan-circle-dock", group="tools")

    # -- the project's scan circles ---------------------------------------------------------------------------

    def stored(self) -> list[ScanCircle]:
        return self.session.project.scan_circles()

    def measurer(self) -> Callable:
        return lambda mesh, traces, circle, sight, rock: measure_scan_circle(mesh, traces, circle, sight=sight,
                                                                             rock=rock)

    def report(self, measure: WindowMeasure) -> dict:
        return window_report(measure, self.session.project.origin, self.session.similarity())

    def summary_line(self, report: dict) -> str:
        name = f"{report['id']}" + (f" ({report['name']})" if report["name"] else "")
        return (f"{name}: r {report['radius_m']:g} m, {report['edge_cuts']} cuts, {report['ends_inside']} ends, "
                f"P21 {report['p21_per_m']:.3f} /m" + ("" if report["unbiased"] else " (biased)"))

    def readout(self, report: dict) -> str:
        text = describe_window(report)
        if len(self.measures) > 1:
            pool = counts_report(pooled_windows(list(self.measures.values())), length_scale(self.session.similarity()))
            text += "\n\n" + describe_pooled_windows(pool, len(self.measures))
        return text

    def _show(self, measures: dict[int, WindowMeasure], problems: dict[int, str]) -> None:
        self.viewer.plots_panel.set_scan_circles(list(measures.values()))
        super()._show(measures, problems)

    def load_settings(self) -> None:
        self.radius.blockSignals(True)
        self.radius.setValue(float(self.session.setting(RADIUS_SETTING, DEFAULT_RADIUS)))
        self.radius.blockSignals(False)

    # -- laying -----------------------------------------------------------------------------------------------

    def handle_click(self, x: int, y: int, additive: bool) -> bool:
        """While the tool is on, a click picks the centre of a new window; True: the click was taken."""
        if not self.action.isChecked() or self.viewer.mesh is None:
            return False
        task = Task("Picking the mesh", pick_mesh, self.viewer.mesh, *self.viewer.view.line_of_sight(x, y))
        self._laying[task] = ""
        task.signals.done.connect(self._picked)
        task.signals.failed.connect(self._failed)
        self.session.jobs.start(task)
        return True

    def _picked(self, point: np.ndarray | None) -> None:
        if self._drop_sender() is None:  # the tool was turned off meanwhile
            return
        if point is None:
            self.message.setText("no mesh under the cursor: click on the rock")
            self.laid.emit(None)
        else:
            self.lay(point)

    def lay(self, centre: np.ndarray) -> None:
        """Measure a window of the radius at `centre` (local frame) on a worker, then store it (one edit)."""
        try:  # the radius is given in the readouts' frame
            circle = ScanCircle(centre, self.radius.value() / length_scale(self.session.similarity()))
        except TracemapError as exc:
            self._refused(exc)
            return
        self.message.setText("measuring the scan circle…")
        self._start(Task("Measuring a scan circle", _measure_new, self.viewer.mesh, self.survey_of(),
                         self.session.traces3d(), [circle]), "Lay scan circle")

    def lay_grid(self) -> None:
        """Cover the face with windows of the radius (`engine.scan_circle.grid_scan_circles`), measured on a
        worker and stored as one edit."""
        if self.viewer.mesh is None:
            return
        similarity = self.session.similarity()
        up = np.array([0.0, 0.0, 1.0]) if similarity is None else similarity.R.T @ np.array([0.0, 0.0, 1.0])
        self.message.setText("laying a grid of scan circles…")
        self._start(Task("Laying a grid of scan circles", _lay_grid, self.viewer.mesh, self.survey_of(),
                         self.session.traces3d(), self.radius.value() / length_scale(similarity), up),
                    "Lay a grid of scan circles")

    def _start(self, task: Task, text: str) -> None:
        self._laying[task] = text
        task.signals.done.connect(self._measured_new)
        task.signals.failed.connect(self._failed)
        self.session.jobs.start(task)

    def _measured_new(self, measures: list[WindowMeasure]) -> None:
        text = self._drop_sender()
        if text is None:
            return
        name = self.name.text().strip()
        circles = self.store([m.circle if not name else
                              replace(m.circle, name=name if len(measures) == 1 else f"{name} {k + 1}")
                              for k, m in enumerate(measures)], text)
        if circles is None:
            self.laid.emit(None)
            return
        self.name.clear()
        stored = [replace(m, circle=c) for m, c in zip(measures, circles)]
        self.message.setText(f"stored: {self.summary_line(self.report(stored[0]))}" if len(stored) == 1
                             else f"stored {len(stored)} scan circles")
        self.laid.emit(stored)

    def _drop_sender(self) -> str | None:
        """Forget the task that sent the signal being handled and return its text; None if it is not one of
        ours (cancelled when the tool was turned off)."""
        task = next((t for t in self._laying if t.signals is self.sender()), None)
        return None if task is None else self._laying.pop(task)

    def _failed(self, exc: BaseException) -> None:
        self._drop_sender()
        if isinstance(exc, TracemapError):
            self._refused(exc)
        else:
            show_error(self.viewer, "Laying a scan circle", exc)
            self.laid.emit(None)

    def _refused(self, exc: TracemapError) -> None:
        self.message.setText(f"{describe(exc)}. Click a point on the rock")
        self.laid.emit(None)

    def _toggled(self, on: bool) -> None:
        for task in self._laying:
            task.cancel()
        self._laying = {}
        if on:
            self.dock.show()
            self.dock.raise_()
            self.message.setText("Click the centre of a scan circle on the rock")

    # -- drawing ----------------------------------------------------------------------------------------------

    def draw(self) -> None:
        """The measured windows' edges, a mark at each crossing and at each end inside."""
        add_scan_circles(self.viewer.view.plotter, list(self.measures.values()) if self.viewer.mesh is not None else [])
        self.viewer.view.refresh()


def _measure_new(mesh: Mesh, sight: Callable[[Progress], Sight], traces: list[Trace3D], circles: list[ScanCircle],
                 *, progress: Progress) -> list[WindowMeasure]:
    """New windows measured on the rock the photos see (`sight(progress)` builds the survey if needed)."""
    survey = sight(progress)
    progress(0.5, "measuring the scan circle")
    return [measure_scan_circle(mesh, traces, circle, sight=survey) for circle in circles]


def _lay_grid(mesh: Mesh, sight: Callable[[Progress], Sight], traces: list[Trace3D], radius: float, up: np.ndarray,
              *, progress: Progress) -> list[WindowMeasure]:
    """A grid of windows over the face, measured."""
    survey = sight(progress)
    circles = grid_scan_circles(mesh, radius, up=up)
    measures = []
    for k, circle in enumerate(circles):
        progress(0.5 + 0.5 * k / len(circles), f"measuring window {k + 1} of {len(circles)}")
        measures.append(measure_scan_circle(mesh, traces, circle, sight=survey))
    return measures
