"""The intensity maps dock of the 3D viewer: P21 or P32 colouring the mesh, and computing them anew.

The maps are the per-vertex values of `tracemap analyse --radius` (engine.analysis.intensity_maps, MATHS §8):
"p21", "p21:set<k>", "p32", "p32:set<k>". The panel picks one to colour the mesh with (vertices outside the
imaged area are NaN, drawn grey), sets its colour range, and computes the maps again with another sphere
radius on a worker. Computing stores only the maps: unlike `tracemap analyse` it leaves the terminations and
components of the traces, which may have been edited by hand, as they are. The maps are results derived
from the traces, like the CLI's, so storing them is not an undoable edit: the worker writes them itself
(through its own connection to the project), since a few MB of blobs took the GUI thread 50–100 ms.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import QComboBox, QFormLayout, QHBoxLayout, QLabel, QPushButton, QVBoxLayout, QWidget

from engine.analysis import intensity_maps, intensity_summary
from engine.cameras import Camera
from engine.errors import Progress, report
from engine.intensity import imaged_faces
from engine.mesh import Mesh
from engine.project import Project
from engine.register import length_scale
from engine.traces import Trace3D
from tracemap_gui.error_dialog import show_error
from tracemap_gui.length_box import length_box
from tracemap_gui.mesh_tracer import MeshTracer
from tracemap_gui.workers import Task

if TYPE_CHECKING:
    from tracemap_gui.viewer3d import Viewer3D

QUANTITIES = {"None": None, "P21": "p21", "P32": "p32"}
UNITS = {"p21": "m⁻¹", "p32": "m²/m³ = m⁻¹"}
ALL_SETS = "all sets"
RANGES = {"auto (min–max)": 0.0, "2–98 %": 2.0, "5–95 %": 5.0}  # percent of the values left out at each end
IDEAL_SPACINGS = 10  # a radius of this many mesh spacings gives a smooth map (engine.intensity)
DEFAULT_RADIUS = 0.5  # m, before the mesh is known
SETTING = "viewer3d/map"


class MapsPanel(QWidget):
    """Which map colours the mesh (`map_name`, its `values` and colour range `clim`), and a new radius."""

    changed = Signal()  # the map, its values or its colour range changed: the viewer redraws

    def __init__(self, viewer: Viewer3D):
        super().__init__(viewer)
        self.setObjectName("maps-panel")
        self.viewer = viewer
        self.session = viewer.session
        self.map_name: str | None = None
        self.values: np.ndarray | None = None
        self.clim: tuple[float, float] | None = None
        self._info: dict = {}  # how the shown map was made: {"radius": metres}
        self._names: list[str] = []
        self._build()
        self.dock = viewer.add_panel(self, "Intensity maps", "maps-dock", group="layers")
        # queued: reading a map (MB of blobs) in a pass of the event loop of its own, not in the one in which
        # every window reloads
        self.session.opened.connect(self._reload, Qt.ConnectionType.QueuedConnection)
        self.session.registration_changed.connect(self._reload)
        self.session.closed.connect(self._reload)
        viewer.mesh_loaded.connect(self._mesh_loaded)
        self._reload()

    def _build(self) -> None:
        self.quantity_box = _combo("map-quantity", QUANTITIES)
        self.subset_box = _combo("map-subset", [])
        self.range_box = _combo("map-range", RANGES)
        self.info = QLabel(self)
        self.info.setObjectName("map-info")
        self.radius_box = length_box(self, "map-radius", "radius of the sphere P21 is measured in at every vertex",
                                     low=0.001, high=1.0e4, decimals=3)
        self.radius_box.setValue(DEFAULT_RADIUS)
        self.compute_button = QPushButton("Compute", self)
        self.compute_button.setObjectName("map-compute")
        self.hint = QLabel(self)  # short lines, not word wrap: docks do not grow for wrapped labels
        radius_row = QHBoxLayout()
        radius_row.addWidget(self.radius_box, 1)
        radius_row.addWidget(self.compute_button)
        form = QFormLayout()
        form.addRow("Map", self.quantity_box)
        form.addRow("Traces", self.subset_box)
        form.addRow("Colours", self.range_box)
        form.addRow("Radius", radius_row)
        layout = QVBoxLayout(self)
        layout.addLayout(form)
        layout.addWidget(self.info)
        layout.addWidget(self.hint)
        layout.addStretch(1)
        self.quantity_box.currentTextChanged.connect(self._select)
        self.subset_box.currentTextChanged.connect(self._select)
        self.range_box.currentTextChanged.connect(self._rescale)
        self.compute_button.clicked.connect(self.compute)

    # -- showing a map --------------------------------------------------------------------------------

    def _reload(self) -> None:
        """Read the stored maps' names and show the remembered map (or none)."""
        self._names = self.session.project.map_names() if self.session.is_open else []
        wanted = self.session.setting(SETTING)
        wanted = wanted if wanted in self._names else None
        self._set_boxes(wanted)
        self._show(wanted)
        made = self._info or (self.session.project.map_info(self._names[0]) if self._names else {})
        if made.get("radius"):  # start from the radius of the stored maps
            self.radius_box.setValue(float(made["radius"]) * self._scale())

    def _set_boxes(self, name: str | None) -> None:
        """Put the two boxes on `name` (quantity, then the sets it has) without reacting to it."""
        quantity, _, subset = (name or "").partition(":")
        label = next(k for k, v in QUANTITIES.items() if v == (quantity or None))
        for box in (self.quantity_box, self.subset_box):
            box.blockSignals(True)
        self.quantity_box.setCurrentText(label)
        self.subset_box.clear()
        subsets = sorted(n.partition(":")[2] for n in self._names if n.partition(":")[0] == quantity)
        self.subset_box.addItems([_subset_label(s) for s in subsets])
        self.subset_box.setCurrentText(_subset_label(subset))
        for box in (self.quantity_box, self.subset_box):
            box.blockSignals(False)

    def _select(self) -> None:
        quantity = QUANTITIES[self.quantity_box.currentText()]
        subset = _subset_name(self.subset_box.currentText())
        name = None if quantity is None else f"{quantity}:{subset}" if subset else quantity
        if name is not None and name not in self._names:  # the other quantity lacks this set: show all sets
            name = quantity if quantity in self._names else None
        if quantity is not None and name is None:
            self.viewer.statusBar().showMessage(f"no {quantity.upper()} map is stored: compute the maps"
                                                + (" after Orient has found the sets" if quantity == "p32" else ""),
                                                8000)
        self._set_boxes(name)
        self._show(name)

    def _show(self, name: str | None) -> None:
        self.map_name = name
        self.values, self._info = (None, {}) if name is None else self.session.project.vertex_map(name)
        if self.values is not None:  # per metre of the registered frame, as the exports
            self.values = self.values / self._scale()
        self.session.set_setting(SETTING, name)
        self._rescale()

    def _scale(self) -> float:
        """The registration's scale: radii and P21/P32 are read and typed in its frame (1 without one)."""
        return length_scale(self.session.similarity()) if self.session.is_open else 1.0

    def _rescale(self) -> None:
        """Colour range and the numbers of the map; then the viewer redraws."""
        self.clim = None
        self.info.clear()
        if self.values is not None:
            finite = self.values[np.isfinite(self.values)]
            if len(finite):
                cut = RANGES[self.range_box.currentText()]
                lo, hi = np.percentile(finite, [cut, 100.0 - cut])
                self.clim = (float(lo), float(max(hi, lo + 1e-12)))  # a constant map still needs a range
            self.info.setText(self._describe(finite))
        if self.session.is_open:  # a closed project's scene is cleared, not redrawn
            self.changed.emit()

    def _describe(self, finite: np.ndarray) -> str:
        unit = UNITS.get(self.map_name.partition(":")[0], "")
        radius = self._info.get("radius")
        text = f"radius {radius * self._scale():g} m, " if radius else ""
        text += f"{len(finite) / len(self.values):.0%} of the vertices imaged"
        if len(finite):
            text += f"\nmedian {np.median(finite):.3g} {unit}, colours {self.clim[0]:.3g}–{self.clim[1]:.3g}"
        return text

    # -- computing ------------------------------------------------------------------------------------

    def _mesh_loaded(self, mesh: Mesh) -> None:
        """Show the radius bound of this mesh; start from ten spacings when no map is stored."""
        spacing = mesh.mean_edge_length * self._scale()
        self.hint.setText(f"mesh spacing {spacing:.3g} m:\nradius ≥ {spacing:.3g} m, "
                          f"ideally ≥ {IDEAL_SPACINGS * spacing:.3g} m")
        if not self._names:
            self.radius_box.setValue(IDEAL_SPACINGS * spacing)

    def compute(self) -> None:
        """P21/P32 maps with the radius of the spin box, on a worker; stored and shown when done."""
        mesh, radius = self.viewer.mesh, self.radius_box.value()
        scale = self._scale()
        problem = _problem(mesh, radius, self.session.traces3d() if self.session.is_open else [], scale)
        if problem:
            show_error(self, "Computing the intensity maps", problem)
            return
        task = Task(f"Intensity maps (radius {radius:g} m)", _compute_maps, mesh, self.session.traces3d(),
                    self.session.cameras(), self.session.project.result("sets") or [], radius / scale,
                    self.session.project, self.session.mesh_tracer)
        task.signals.done.connect(lambda maps: self._stored(maps, radius))
        task.signals.failed.connect(lambda exc: show_error(self, "Computing the intensity maps", exc))
        task.signals.ended.connect(lambda: self.compute_button.setEnabled(True))
        self.compute_button.setEnabled(False)
        self.session.jobs.start(task)

    def _stored(self, maps: dict[str, np.ndarray], radius: float) -> None:
        self._names = self.session.project.map_names()
        self._set_boxes(self.map_name or "p21")
        self._show(self.map_name or "p21")
        self.viewer.statusBar().showMessage(f"{len(maps)} intensity maps stored, radius {radius:g} m", 5000)


def _combo(name: str, items) -> QComboBox:
    box = QComboBox()
    box.setObjectName(name)
    box.addItems(list(items))
    return box


def _subset_label(subset: str) -> str:
    """Map-name suffix → box label: "" → "all sets", "set1" → "set 1"."""
    return subset.replace("set", "set ") if subset else ALL_SETS


def _subset_name(label: str) -> str:
    """Box label → map-name suffix, the inverse of `_subset_label`."""
    return "" if label in ("", ALL_SETS) else label.replace(" ", "")


def _problem(mesh: Mesh | None, radius: float, traces: list[Trace3D], scale: float = 1.0) -> str | None:
    """Why maps cannot be computed now (None: they can). The radius bound is engine.intensity's; `radius` and
    what is said are in the registered frame (`scale` times the mesh's)."""
    if mesh is None:
        return "the mesh is still loading; try again once it is shown"
    if not traces:
        return "there are no 3D traces to map; extract traces first"
    spacing = mesh.mean_edge_length * scale
    if radius < spacing:
        return (f"radius {radius:g} m is below the mesh spacing ({spacing:.3g} m, the mean edge length): "
                f"enter at least {spacing:.3g} m, ideally {IDEAL_SPACINGS * spacing:.3g} m or more")
    return None


def _compute_maps(mesh: Mesh, traces: list[Trace3D], cameras: dict[str, Camera], sets: list[dict],
                  radius: float, project: Project, tracers: MeshTracer, *,
                  progress: Progress) -> dict[str, np.ndarray]:
    """The maps of `engine.analysis.intensity_maps` over the area the photos saw, stored in `project` in one
    transaction (runs on a worker)."""
    tracer = tracers.of(mesh, progress=lambda f, m: report(progress, 0.05 * f, m))
    imaged = imaged_faces(mesh, cameras, tracer, progress=lambda f, m: report(progress, 0.05 + 0.1 * f, m))
    maps = intensity_maps(mesh, traces, radius=radius, imaged=imaged, sets=sets,
                          progress=lambda f, m: report(progress, 0.15 + 0.8 * f, m))
    summary = intensity_summary(traces, maps, radius=radius, imaged_area=float(mesh.face_areas[imaged].sum()))
    report(progress, 0.95, "storing the maps")  # the last point where Cancel leaves the stored maps as they were
    handle = project.for_thread()
    try:
        with handle.transaction() as db:  # the maps and what summary.json says of them, together
            handle.set_vertex_maps(maps, {"radius": radius}, db)
            handle.set_result("intensity", summary, db)
            handle.record_basis(["intensity"], traces, db)
    finally:
        handle.close()
    return maps
