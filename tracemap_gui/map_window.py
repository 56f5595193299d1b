"""File → Analyse a 2D map…: `tracemap analyse-map` in a window of its own, with or without a project open.

A fracture map digitised in a GIS (trace LineStrings and the sampling-area polygon, as GeoJSON, GeoPackage
or Shapefile) gets the terminations, topology, censored lengths and intensity a project's traces get
(`engine.maps2d`). The analysis runs on a worker, as the AD p-values' bootstrap takes seconds; it writes all
or nothing into the output folder, and the window shows the figures it wrote, one tab each, and what it
found. The form as last run is a user setting ("map_analysis", QSettings), offered again next time.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from PySide6.QtCore import QSettings, Qt
from PySide6.QtGui import QCloseEvent, QImage
from PySide6.QtWidgets import (QDoubleSpinBox, QFormLayout, QLabel, QLineEdit, QMainWindow, QPlainTextEdit,
                               QPushButton, QSpinBox, QSplitter, QTabWidget, QWidget)

from engine.errors import InputError
from engine.lengths import N_BOOTSTRAP
from engine.maps2d import SET_COLUMNS, SNAP, MapOutput, analyse_map, report_lines
from tracemap_gui.error_dialog import show_error
from tracemap_gui.new_project import PathField
from tracemap_gui.plots_panel import FigurePicture
from tracemap_gui.workers import Jobs, ProgressPanel, Task

MAP_FILTER = "trace maps (*.geojson *.json *.gpkg *.shp);;all files (*)"
SETTING = "map_analysis"
MAX_MAP_UNITS = 1e9  # spin box limit: beyond any map, in metres or feet


class MapLength(QDoubleSpinBox):
    """A length in map units shown without the trailing zeros of its six decimals (0.001, 20, 1500000)."""

    def textFromValue(self, value: float) -> str:
        return f"{value:.6f}".rstrip("0").rstrip(".")


@dataclass(frozen=True)
class MapRequest:
    """What the form asks for: `engine.maps2d.analyse_map`'s arguments (map units; None where not asked)."""

    traces: Path
    area: Path
    output: Path
    snap: float = SNAP
    n_bootstrap: int = N_BOOTSTRAP
    grid: float | None = None
    grid_radius: float | None = None
    scan_circle_grid: float | None = None
    scan_circles: tuple[tuple[float, float, float], ...] = ()
    layer: str | None = None
    area_layer: str | None = None
    set_column: str | None = None


def analyse(request: MapRequest, *, progress) -> MapOutput:
    """The analysis of the map (a Task's function, on a worker)."""
    return analyse_map(request.traces, request.area, request.output, snap=request.snap, layer=request.layer,
                       area_layer=request.area_layer, set_column=request.set_column,
                       n_bootstrap=request.n_bootstrap, grid=request.grid, grid_radius=request.grid_radius,
                       scan_circle_grid=request.scan_circle_grid,
                       scan_circles=[((x, y), r) for x, y, r in request.scan_circles], progress=progress)


class MapForm(QWidget):
    """The files, the options of `tracemap analyse-map` and Run; `parse()` reads them or says what is wrong."""

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        self.traces = PathField("map-traces", {"File…": "open"}, MAP_FILTER, self)
        self.area = PathField("map-area", {"File…": "open"}, MAP_FILTER, self)
        self.output = PathField("map-output", {"Folder…": "folder"}, parent=self)
        self.snap = self._length("map-snap", SNAP, minimum=1e-6, tip="ends this close to a trace or the area's "
                                 "edge abut it (Y, E nodes); fractopo's snap threshold")
        self.bootstrap = QSpinBox(self, objectName="map-bootstrap", minimum=0, maximum=99_999, value=N_BOOTSTRAP)
        self.bootstrap.setToolTip("samples of the Anderson–Darling p-values of the length fits (0: no p-values)")
        self.grid = self._length("map-grid", 0.0, special="none", tip="cell of a P21/P20 map: a disc about each "
                                 "cell's centre, its part inside the area")
        self.grid_radius = self._length("map-grid-radius", 0.0, special="1.5 cells", tip="radius of the P21 map's "
                                        "discs")
        self.circle_grid = self._length("map-circle-grid", 0.0, special="none", tip="a circle inventory: scan "
                                        "circles of this radius 2R apart, those wholly inside the area")
        self.circles = QLineEdit(self, objectName="map-scan-circles", placeholderText="x y r; x y r …")
        self.circles.setToolTip("Mauldon's scan circles inside the area (map units); a circular area gets them "
                                "without any")
        self.layer = QLineEdit(self, objectName="map-layer", placeholderText="the file's only layer")
        self.area_layer = QLineEdit(self, objectName="map-area-layer", placeholderText="the file's only layer")
        self.set_column = QLineEdit(self, objectName="map-set-column", placeholderText=" or ".join(SET_COLUMNS))
        self.run = QPushButton("Run", self, objectName="map-run")
        self.message = QLabel("", self, objectName="map-message", wordWrap=True)
        self.message.setStyleSheet("color: #b00020")
        form = QFormLayout(self)
        for label, field in (("Traces", self.traces), ("Sampling area", self.area), ("Output folder", self.output),
                             ("Snap", self.snap), ("Bootstrap", self.bootstrap), ("P21 map cell", self.grid),
                             ("P21 disc radius", self.grid_radius), ("Circle inventory R", self.circle_grid),
                             ("Scan circles", self.circles), ("Traces layer", self.layer),
                             ("Area layer", self.area_layer), ("Set column", self.set_column)):
            form.addRow(label, field)
        form.addRow(self.message)
        form.addRow(self.run)

    def _length(self, name: str, value: float, *, minimum: float = 0.0, special: str = "", tip: str) -> MapLength:
        box = MapLength(self, objectName=name, decimals=6, minimum=minimum, maximum=MAX_MAP_UNITS, value=value)
        box.setSpecialValueText(special)  # shown at the minimum, which then means "not asked for"
        box.setToolTip(f"{tip} (map units)")
        return box

    def parse(self) -> MapRequest:
        """The request, or InputError naming the field and what it expects."""
        traces = self._existing(self.traces, "Traces", "the trace LineStrings")
        area = self._existing(self.area, "Sampling area", "the polygon of the mapped area, where traces are "
                                                          "censored and which P21 is divided by")
        if not self.output.text:
            raise InputError(None, "Output folder: expected where to write the tables and figures; none given")
        output = Path(self.output.text).expanduser()
        if output.exists() and not output.is_dir():
            raise InputError(output, "Output folder: is a file; expected a folder (made if it does not exist)")
        grid, radius = self.grid.value() or None, self.grid_radius.value() or None
        if radius is not None and grid is None:
            raise InputError(None, "P21 disc radius: the map's discs need a P21 map cell")
        return MapRequest(traces, area, output, snap=self.snap.value(), n_bootstrap=self.bootstrap.value(),
                          grid=grid, grid_radius=radius, scan_circle_grid=self.circle_grid.value() or None,
                          scan_circles=self._scan_circles(), layer=self.layer.text().strip() or None,
                          area_layer=self.area_layer.text().strip() or None,
                          set_column=self.set_column.text().strip() or None)

    @staticmethod
    def _existing(field: PathField, label: str, what: str) -> Path:
        if not field.text:
            raise InputError(None, f"{label}: expected the file of {what}; none given")
        path = Path(field.text).expanduser()
        if not path.is_file():
            raise InputError(path, f"{label}: no such file; expected the file of {what}")
        return path

    def _scan_circles(self) -> tuple[tuple[float, float, float], ...]:
        circles = []
        for part in filter(None, (p.strip() for p in self.circles.text().split(";"))):
            try:
                x, y, r = (float(v) for v in part.replace(",", " ").split())
            except ValueError:
                raise InputError(None, f"Scan circles: expected 'x y r' for each circle, separated by ';'; "
                                       f"got {part!r}") from None
            if not r > 0:
                raise InputError(None, f"Scan circles: expected a radius above 0; got {part!r}")
            circles.append((x, y, r))
        return tuple(circles)

    def state(self) -> dict:
        """The form as a user setting."""
        return {"traces": self.traces.text, "area": self.area.text, "output": self.output.text,
                "snap": self.snap.value(), "bootstrap": self.bootstrap.value(), "grid": self.grid.value(),
                "grid_radius": self.grid_radius.value(), "circle_grid": self.circle_grid.value(),
                "scan_circles": self.circles.text(), "layer": self.layer.text(),
                "area_layer": self.area_layer.text(), "set_column": self.set_column.text()}

    def restore(self, state: dict) -> None:
        """Fill the form from `state()`; a value of the wrong kind is left at its default."""
        for key, edit in (("traces", self.traces.edit), ("area", self.area.edit), ("output", self.output.edit),
                          ("scan_circles", self.circles), ("layer", self.layer), ("area_layer", self.area_layer),
                          ("set_column", self.set_column)):
            if isinstance(state.get(key), str):
                edit.setText(state[key])
        for key, box in (("snap", self.snap), ("bootstrap", self.bootstrap), ("grid", self.grid),
                         ("grid_radius", self.grid_radius), ("circle_grid", self.circle_grid)):
            if isinstance(state.get(key), (int, float)):
                box.setValue(state[key])


class MapWindow(QMainWindow):
    """The form on the left; the figures written and a summary of the findings, a tab each, on the right."""

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        self.setWindowTitle("tracemap: 2D map")
        self.setObjectName("map-window")
        self.jobs = Jobs(self)
        self.form = MapForm()
        self.form.run.clicked.connect(self.run_form)
        self.tabs = QTabWidget(objectName="map-tabs")
        self.tabs.addTab(QLabel("Choose a trace map and its sampling area, then Run.",
                                alignment=Qt.AlignmentFlag.AlignCenter), "Results")
        splitter = QSplitter()
        splitter.addWidget(self.form)
        splitter.addWidget(self.tabs)
        splitter.setStretchFactor(1, 1)
        self.setCentralWidget(splitter)
        self.statusBar().addPermanentWidget(ProgressPanel(self.jobs, self))
        self.jobs.busy.connect(lambda busy: self.form.run.setEnabled(not busy))
        self.form.restore(_setting())
        self.output: MapOutput | None = None

    def run_form(self) -> Task | None:
        """Run what the form asks for; a field that is wrong is said under the form, and nothing runs."""
        try:
            request = self.form.parse()
        except InputError as exc:
            self.form.message.setText(str(exc))
            return None
        self.form.message.clear()
        QSettings().setValue(SETTING, json.dumps(self.form.state()))
        return self.run(request)

    def run(self, request: MapRequest) -> Task:
        """Analyse on a worker; the tabs show what it wrote, a dialog why it failed (and nothing was written)."""
        task = Task("Analysing the map", analyse, request)
        task.signals.done.connect(self.show_output)
        task.signals.failed.connect(lambda exc: show_error(self, f"Analysing {request.traces}", exc))
        task.signals.cancelled.connect(lambda: self.statusBar().showMessage("analysis cancelled", 5000))
        self.jobs.start(task)
        return task

    def show_output(self, output: MapOutput) -> None:
        self.output = output
        self.tabs.clear()
        for plot in output.plots.values():
            if plot.figure is None:
                page = QLabel(plot.reason, alignment=Qt.AlignmentFlag.AlignCenter, wordWrap=True)
            else:
                page = FigurePicture()
                page.set_image(QImage(str(next(f for f in output.files if f.name == f"{plot.name}.png"))))
            page.setObjectName(f"map-{plot.name}")
            self.tabs.addTab(page, plot.title)
        summary = QPlainTextEdit("\n".join(report_lines(output.analysis)), objectName="map-summary", readOnly=True)
        self.tabs.addTab(summary, "Summary")
        folder = output.files[0].parent
        self.statusBar().showMessage(f"wrote {len(output.files)} files to {folder}", 15_000)

    def closeEvent(self, event: QCloseEvent) -> None:
        self.jobs.cancel_all()  # nothing is written by a cancelled analysis
        super().closeEvent(event)


def _setting() -> dict:
    """The form last run, or {} when there is none (or it is not readable)."""
    try:
        state = json.loads(QSettings().value(SETTING, "{}"))
    except (TypeError, ValueError):
        return {}
    return state if isinstance(state, dict) else {}
