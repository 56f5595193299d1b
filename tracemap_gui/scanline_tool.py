"""The 3D viewer's Scanline tool: virtual scanlines laid on the outcrop, read as P10 and spacing per set.

With the tool on, two clicks on the mesh lay a scanline between the points picked, as a tape is stretched
between two nails; it is measured on a worker (`engine.scanline.measure_scanline`: the traces crossing the
rock under it, P10, Terzaghi-weighted P10, spacing and normal spacing per set, P32) and stored as one
undoable edit. Stored scanlines are listed with their readouts (in the registered frame, if any) and drawn
as lines with a mark at every crossing; they are measured again when the traces or their sets change, and
exported by `tracemap export` (scanlines.csv, summary.json). Picks and measurements run on workers (both
search the mesh's face k-d tree, seconds to build on millions of faces); a newer click supersedes them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pyvista as pv
from PySide6.QtCore import Signal
from PySide6.QtWidgets import (QFileDialog, QFormLayout, QHBoxLayout, QLabel, QLineEdit, QPushButton, QSpinBox,
                               QVBoxLayout, QWidget)

from engine.errors import Progress, TracemapError
from engine.plots import save_figure, write_table_csv
from engine.register import length_scale
from engine.render import MARK_SIZE, SCANLINE_COLOR, add_scanlines
from engine.scanline import (Scanline, ScanlineMeasure, describe_pooled, describe_scanline, level_scanlines,
                             measure_scanline, pooled, scanline_plot, scanline_report)
from tracemap_gui.commands import SCANLINES
from tracemap_gui.error_dialog import describe, show_error
from tracemap_gui.length_box import length_box
from tracemap_gui.sample_tool import SampleTool
from tracemap_gui.workers import Task, pick_mesh

if TYPE_CHECKING:
    from engine.mesh import Mesh
    from engine.sight import Sight
    from engine.traces import Trace3D
    from tracemap_gui.viewer3d import Viewer3D

REACH_SETTING = "scanline/reach"
START_ACTOR = "scanline-start"
DEFAULT_LEVELS = 5
LEVELS_BOX_PX = 64


class ScanlineTool(SampleTool):
    """Lay, list, read and remove scanlines in one 3D viewer (a dock and a checkable tool action)."""

    laid = Signal(object)  # the ScanlineMeasure of a scanline just stored, or None when none could be laid
    surveyed = Signal(object)  # the ScanlineMeasures of the level scanlines just stored, or None
    noun = "scanline"
    storage = SCANLINES

    def __init__(self, viewer: Viewer3D):
        super().__init__(viewer)
        self.start: np.ndarray | None = None  # the first end picked (local frame)
        self._picks: list[Task] = []  # picks in click order: a second click may come before the first is found
        self._found: dict[Task, np.ndarray | None] = {}  # what the picks still queued behind an earlier one found
        self._laying: set[Task] = set()
        self.action = viewer.add_tool("Scanline", "W", "Click two points on the rock to lay a scanline between them")
        self.action.toggled.connect(self._toggled)
        self._build_dock()
        self.watch()

    def _build_dock(self) -> None:
        panel = QWidget()
        self.message = QLabel("Turn on the Scanline tool (W) and click two points on the rock", panel)
        self.message.setObjectName("scanline-message")
        self.message.setWordWrap(True)
        self.reach = length_box(panel, "scanline-reach", "how far from the straight line the rock under it may lie "
                                "(a new scanline's); auto: a tenth of its length, at least 0.5 m", low=0.0,
                                high=1000.0, decimals=2, step=0.1)
        self.reach.setSpecialValueText("auto")  # shown for 0; short, so that the dock keeps its width
        self.reach.valueChanged.connect(lambda value: self.session.set_setting(REACH_SETTING, value))
        self.name = QLineEdit(panel)
        self.name.setObjectName("scanline-name")
        self.name.setPlaceholderText("optional, e.g. bench 2 north")
        self.build_list(panel)
        self.export_button = QPushButton("Export plot…", panel)
        self.export_button.setObjectName("scanline-export")
        self.export_button.setToolTip("the selected scanline's cumulative crossings per set, as PNG or SVG, with its "
                                      "data as CSV beside it (what `tracemap plot` writes)")
        self.export_button.clicked.connect(self._ask_export)
        self.levels = QSpinBox(panel)
        self.levels.setObjectName("scanline-levels")
        self.levels.setRange(1, 100)
        self.levels.setValue(DEFAULT_LEVELS)
        self.levels.setMaximumWidth(LEVELS_BOX_PX)  # narrow, as the dock's other rows: its width is the docks'
        self.levels_button = QPushButton("Lay", panel)
        self.levels_button.setObjectName("scanline-lay-levels")
        self.levels_button.setToolTip("lay this many level scanlines along the outcrop at even heights, 1 m clear "
                                      "of its foot, top and ends (`tracemap scanline --levels`)")
        self.levels_button.clicked.connect(self.lay_levels)
        survey_row = QHBoxLayout()
        survey_row.addWidget(self.levels)
        survey_row.addWidget(self.levels_button)
        form = QFormLayout()
        form.addRow("Reach", self.reach)
        form.addRow("Name", self.name)
        form.addRow("Levels", survey_row)
        layout = QVBoxLayout(panel)
        layout.addWidget(self.message)
        layout.addLayout(form)
        layout.addWidget(QLabel("Stored scanlines", panel))
        layout.addWidget(self.list)
        layout.addWidget(self.details)
        buttons = QHBoxLayout()
        buttons.addWidget(self.remove_button)
        buttons.addWidget(self.export_button)
        layout.addLayout(buttons)
        self.dock = self.viewer.add_panel(panel, "Scanlines", "scanline-dock", group="tools")

    # -- the project's scanlines ------------------------------------------------------------------------------

    def stored(self) -> list[Scanline]:
        return self.session.project.scanlines()

    def measurer(self) -> Callable:
        sets = self.session.project.result("sets") or []
        return lambda mesh, traces, line, sight, rock: measure_scanline(mesh, traces, line, sets=sets, sight=sight,
                                                                        rock=rock)

    def report(self, measure: ScanlineMeasure) -> dict:
        return scanline_report(measure, self.session.project.origin, self.session.similarity())

    def summary_line(self, report: dict) -> str:
        return _summary_line(report)

    def readout(self, report: dict) -> str:
        text = describe_scanline(report)
        if len(self.measures) > 1:
            text += "\n\n" + describe_pooled(pooled(list(self.measures.values()), self.session.similarity()),
                                             len(self.measures))
        return text

    def load_settings(self) -> None:
        self.reach.blockSignals(True)
        self.reach.setValue(float(self.session.setting(REACH_SETTING, 0.0)))
        self.reach.blockSignals(False)

    def _show(self, measures: dict[int, ScanlineMeasure], problems: dict[int, str]) -> None:
        self.viewer.plots_panel.set_scanlines(list(measures.values()))
        super()._show(measures, problems)

    def export_plot(self, path: str | Path) -> None:
        """Write the selected scanline's plot (`engine.scanline.scanline_plot`) to `path` (.png or .svg) and its
        table beside it (.csv)."""
        line = self.selected()
        if line is None or line.id not in self.measures:
            self.message.setText("select a measured scanline to export its plot")
            return
        path = Path(path)
        try:
            plot = scanline_plot(self.measures[line.id], self.session.similarity())
            save_figure(plot.figure, path)
            write_table_csv(plot.table, path.with_suffix(".csv"))
        except Exception as exc:  # noqa: BLE001 - shown to the user; nothing else changes
            show_error(self.viewer, "Exporting the scanline plot", exc)
            return
        self.message.setText(f"saved {path} and {path.with_suffix('.csv').name}")

    def _ask_export(self) -> None:
        line = self.selected()
        name = "scanline.png" if line is None else f"scanline_{line.id}.png"
        path, _ = QFileDialog.getSaveFileName(self.viewer, "Export scanline plot", name,
                                              "PNG image (*.png);;SVG image (*.svg)")
        if path:
            self.export_plot(path if Path(path).suffix else path + ".png")

    # -- laying -----------------------------------------------------------------------------------------------

    def handle_click(self, x: int, y: int, additive: bool) -> bool:
        """While the tool is on, a click picks one end of a new scanline; True: the click was taken."""
        if not self.action.isChecked() or self.viewer.mesh is None:
            return False
        task = Task("Picking the mesh", pick_mesh, self.viewer.mesh, *self.viewer.view.line_of_sight(x, y))
        self._picks.append(task)
        task.signals.done.connect(self._picked)
        task.signals.failed.connect(self._failed)
        self.session.jobs.start(task)
        return True

    def lay(self, start: np.ndarray, end: np.ndarray) -> None:
        """Measure a scanline from `start` to `end` (local frame) on a worker, then store it (one edit)."""
        # given in the readouts' frame; 0 ("automatic") is the engine's default for the line's length
        reach = self.reach.value() / length_scale(self.session.similarity()) or None
        try:
            line = Scanline(start, end, reach=reach, name=self.name.text().strip())
        except TracemapError as exc:
            self._refused(exc)
            return
        self.message.setText("measuring the scanline…")
        task = Task("Measuring a scanline", _measure, self.viewer.mesh, self.survey_of(), self.session.traces3d(),
                    line, self.session.project.result("sets") or [])
        self._laying.add(task)
        task.signals.done.connect(self._measured_new)
        task.signals.failed.connect(self._failed)
        self.session.jobs.start(task)

    def _picked(self, point: np.ndarray | None) -> None:
        """Take the picks' points in click order: the first end, then the other (which lays the scanline)."""
        task = next((t for t in self._picks if t.signals is self.sender()), None)
        if task is None:  # the tool was turned off meanwhile
            return
        self._found[task] = point
        while self._picks and self._picks[0] in self._found:
            self._take(self._found.pop(self._picks.pop(0)))
        self.draw()

    def _take(self, point: np.ndarray | None) -> None:
        if point is None:
            self.message.setText("no mesh under the cursor: click on the rock")
        elif self.start is None:
            self.start = point
            self.message.setText("now click the other end of the scanline")
        else:
            start, self.start = self.start, None
            self.lay(start, point)

    def lay_levels(self) -> None:
        """Lay `levels` level scanlines along the outcrop (`engine.scanline.level_scanlines`), measured on a
        worker and stored as one edit."""
        if self.viewer.mesh is None:
            return
        scale = length_scale(similarity := self.session.similarity())
        up = np.array([0.0, 0.0, 1.0]) if similarity is None else similarity.R.T @ np.array([0.0, 0.0, 1.0])
        self.message.setText("laying level scanlines…")
        task = Task("Laying level scanlines", _lay_levels, self.viewer.mesh, self.survey_of(),
                    self.session.traces3d(), self.levels.value(), 1.0 / scale, up,
                    self.reach.value() / scale or None, self.session.project.result("sets") or [])
        self._laying.add(task)
        task.signals.done.connect(self._surveyed)
        task.signals.failed.connect(self._failed)
        self.session.jobs.start(task)

    def _measured_new(self, measure: ScanlineMeasure) -> None:
        self._laying = {t for t in self._laying if t.signals is not self.sender()}
        stored = self._store([measure], "Lay scanline")
        if stored:
            report = scanline_report(stored[0], self.session.project.origin, self.session.similarity())
            self.message.setText(f"stored: {_summary_line(report)}. Click two more points for another")
        self.laid.emit(stored[0] if stored else None)

    def _surveyed(self, measures: list[ScanlineMeasure]) -> None:
        self._laying = {t for t in self._laying if t.signals is not self.sender()}
        stored = self._store(measures, f"Lay {len(measures)} level scanlines")
        if stored:
            self.message.setText(f"stored {len(stored)} level scanlines")
        self.surveyed.emit(stored)

    def _store(self, measures: list[ScanlineMeasure], text: str) -> list[ScanlineMeasure] | None:
        """Store the measured scanlines as one edit (named with the Name field); their measures with their ids,
        or None when the edit failed (the error was shown)."""
        name = self.name.text().strip()
        lines = [m.line if not name else replace(m.line, name=name if len(measures) == 1 else f"{name} {k + 1}")
                 for k, m in enumerate(measures)]
        stored = self.store(lines, text)
        if stored is None:
            return None
        self.name.clear()
        return [replace(m, line=line) for m, line in zip(measures, stored)]

    def _failed(self, exc: BaseException) -> None:
        """A pick or a measuring failed: drop that pick (the next click starts a scanline again)."""
        sender = self.sender()
        self._picks = [t for t in self._picks if t.signals is not sender]
        self._laying = {t for t in self._laying if t.signals is not sender}
        self.start = None
        if isinstance(exc, TracemapError):
            self._refused(exc)
        else:
            show_error(self.viewer, "Laying a scanline", exc)
            self.laid.emit(None)

    def _refused(self, exc: TracemapError) -> None:
        self.message.setText(f"{describe(exc)}. Click two points on the rock")
        self.draw()
        self.laid.emit(None)

    def _toggled(self, on: bool) -> None:
        for task in [*self._picks, *self._laying]:
            task.cancel()
        self._picks, self._found, self._laying, self.start = [], {}, set(), None
        if on:
            self.dock.show()
            self.dock.raise_()
            self.message.setText("Click one end of the scanline on the rock")
        self.draw()

    # -- drawing ----------------------------------------------------------------------------------------------

    def draw(self) -> None:
        """The stored scanlines, a mark at each crossing, and the first end of the one being laid."""
        plotter = self.viewer.view.plotter
        plotter.remove_actor(START_ACTOR, render=False)
        if self.viewer.mesh is None:
            add_scanlines(plotter, [])
            return
        add_scanlines(plotter, list(self.measures.values()), [ln for ln in self.items if ln.id not in self.measures])
        if self.start is not None:
            plotter.add_mesh(pv.PolyData(self.start[None]), color=SCANLINE_COLOR, point_size=MARK_SIZE,
                             render_points_as_spheres=True, pickable=False, name=START_ACTOR, render=False)
        self.viewer.view.refresh()


def _summary_line(report: dict) -> str:
    name = f"{report['id']}" + (f" ({report['name']})" if report["name"] else "")
    p10 = report["groups"]["all"]["p10_per_m"]
    return f"{name}: {report['length_m']:.2f} m, {report['crossings']} crossings, P10 {p10:.3f} /m"


def _measure(mesh: Mesh, sight: Callable[[Progress], Sight], traces: list[Trace3D], line: Scanline,
             sets: list[dict], *, progress: Progress) -> ScanlineMeasure:
    """A new scanline measured on the rock the photos see (`sight(progress)` builds the survey if needed)."""
    survey = sight(progress)
    progress(0.5, "measuring the scanline")
    return measure_scanline(mesh, traces, line, sets=sets, sight=survey)


def _lay_levels(mesh: Mesh, sight: Callable[[Progress], Sight], traces: list[Trace3D], n: int, margin: float,
                up: np.ndarray, reach: float | None, sets: list[dict], *, progress: Progress) -> list[ScanlineMeasure]:
    """`n` level scanlines laid along the outcrop and measured (a line off the seen rock refuses them all)."""
    survey = sight(progress)
    lines = level_scanlines(mesh, n, margin=margin, up=up, reach=reach)
    measures = []
    for k, line in enumerate(lines):
        progress(0.5 + 0.5 * k / n, f"measuring level {k + 1}")
        measures.append(measure_scanline(mesh, traces, line, sets=sets, sight=survey))
    return measures
