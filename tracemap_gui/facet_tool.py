"""The 3D viewer's Facet tool: fracture planes measured where a fracture face is exposed on the mesh.

With the tool on, a click on the mesh picks a point; the faces within the chosen radius are highlighted and
the plane fitted to their vertices is drawn as a disc, with its dip / dip direction and planarity, or with
the reason it was rejected (`engine.sets.fit_mesh_facet`: planarity 1 − λ3/λ2 below 0.75, or the outcrop
face itself, as CloudCompare Compass checks). Accept stores it as one undoable command. Stored facets are
listed and drawn as discs; they seed the set fitting (`tracemap orient`, `engine.sets.classify_traces`).

The pick (the line of sight cast onto the mesh) and the fit run on workers: both search the mesh's
face-centroid k-d tree (`Mesh.face_tree`), 3–4 s to build at 3.2M faces, which a worker starts as soon as the
tool is turned on. A click or a radius change supersedes the pick or fit still running.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import pyvista as pv
from PySide6.QtCore import QObject, Signal
from PySide6.QtWidgets import QFormLayout, QLabel, QListWidget, QPushButton, QVBoxLayout, QWidget

from engine.errors import Progress, TracemapError
from engine.orientation import normal_to_dip_dipdir
from engine.register import Similarity, length_scale, rotate_directions
from engine.sets import Facet, fit_mesh_facet, mesh_patch
from tracemap_gui.commands import FACETS, EditItems
from tracemap_gui.error_dialog import describe, show_error
from tracemap_gui.length_box import length_box
from tracemap_gui.workers import Task, pick_mesh

if TYPE_CHECKING:
    from engine.mesh import Mesh
    from tracemap_gui.viewer3d import Viewer3D

RADIUS_SETTING = "facet/radius"
DEFAULT_RADIUS = 0.25  # m: a hand-sized patch of an exposed fracture face
PATCH_ACTOR, PREVIEW_ACTOR, STORED_ACTOR = "facet-patch", "facet-preview", "facets"
PATCH_COLOR = (255, 215, 0)
ACCEPTED_COLOR, REJECTED_COLOR, STORED_COLOR = (0, 190, 80), (220, 30, 30), (0, 120, 255)
DISC_OPACITY = 0.6
PREVIEW_OPACITY = 0.4  # the highlighted patch shows through the fitted disc
ON_TOP = -66000  # VTK coincident-topology offset units: the highlight is drawn over the mesh faces it covers


def describe_facet(facet: Facet, similarity: Similarity | None = None) -> str:
    """One line a geologist reads: orientation, planarity, fit and size (in the registered frame if any)."""
    dip, dip_direction = (float(a) for a in normal_to_dip_dipdir(rotate_directions(facet.normal, similarity)))
    scale = length_scale(similarity)
    return (f"dip {dip:.1f}° / dip direction {dip_direction:05.1f}°, planarity {facet.planarity:.2f}, "
            f"rms {scale * facet.rms * 1000:.1f} mm, radius {scale * facet.radius:.2f} m")


class FacetTool(QObject):
    """Pick, preview, accept and remove facets in one 3D viewer (a dock and a checkable tool action)."""

    fitted = Signal(object)  # the facet now on show after a fit, or None when none could be fitted

    def __init__(self, viewer: Viewer3D):
        super().__init__(viewer)
        self.viewer, self.session = viewer, viewer.session
        self.point: np.ndarray | None = None  # the picked point (local frame)
        self.preview: Facet | None = None
        self.facets: list[Facet] = []
        self._task: Task | None = None  # the latest pick or fit; a newer one cancels it
        self._indexed: weakref.ref[Mesh] | None = None  # the mesh whose face tree is built or being built
        self.action = viewer.add_tool("Facet", "F", "Click an exposed fracture face on the mesh to fit a plane to it")
        self.action.toggled.connect(self._toggled)
        self._build_dock()
        self.session.opened.connect(self.reload)
        self.session.registration_changed.connect(self.reload)
        self.session.closed.connect(self._closed)  # bound methods: no call after the tool is deleted
        viewer.mesh_loaded.connect(self._mesh_loaded)
        self.reload()

    def _build_dock(self) -> None:
        panel = QWidget()
        self.message = QLabel("Turn on the Facet tool (F) and click an exposed fracture face", panel)
        self.message.setObjectName("facet-message")
        self.message.setWordWrap(True)
        self.radius = length_box(panel, "facet-radius", "the faces whose centre lies within this distance of the "
                                 "click are fitted", low=0.01, high=1000.0, decimals=2, step=0.05)
        self.radius.valueChanged.connect(self._radius_changed)
        self.accept_button = QPushButton("Accept", panel)
        self.accept_button.setObjectName("facet-accept")
        self.accept_button.clicked.connect(self.accept)
        self.list = QListWidget(panel)
        self.list.setObjectName("facet-list")
        self.remove_button = QPushButton("Remove", panel)
        self.remove_button.setObjectName("facet-remove")
        self.remove_button.clicked.connect(self.remove_selected)
        form = QFormLayout()
        form.addRow("Radius", self.radius)
        layout = QVBoxLayout(panel)
        layout.addWidget(self.message)
        layout.addLayout(form)
        layout.addWidget(self.accept_button)
        layout.addWidget(QLabel("Stored facets (set seeds)", panel))
        layout.addWidget(self.list)
        layout.addWidget(self.remove_button)
        self.dock = self.viewer.add_panel(panel, "Facets", "facet-dock", group="tools")
        self.accept_button.setEnabled(False)

    # -- the project's facets ---------------------------------------------------------------------------------

    def _closed(self) -> None:
        self.action.setChecked(False)  # drops a facet on show
        self.reload()

    def reload(self) -> None:
        """Read the stored facets (after an edit, an undo, or opening a project) and show them."""
        self.facets = self.session.project.facets() if self.session.is_open else []
        self.list.clear()
        similarity = self.session.similarity()
        self.list.addItems([f"{f.id}: {describe_facet(f, similarity)}" for f in self.facets])
        self.radius.blockSignals(True)
        self.radius.setValue(float(self.session.setting(RADIUS_SETTING, DEFAULT_RADIUS)))
        self.radius.blockSignals(False)
        self.draw()

    def accept(self) -> None:
        """Store the facet on show (one undoable edit)."""
        facet = self.preview
        if facet is None or not facet.accepted:
            return
        self.viewer.push(EditItems(self.session, FACETS, [], [facet], "Add facet", self.reload))
        self.point = self.preview = None
        self.message.setText(f"stored: {describe_facet(facet, self.session.similarity())}")
        self.accept_button.setEnabled(False)
        self.draw()

    def remove_selected(self) -> None:
        chosen = [self.facets[i.row()] for i in self.list.selectedIndexes()]
        if chosen:
            self.viewer.push(EditItems(self.session, FACETS, chosen, [], f"Remove {len(chosen)} facets", self.reload))

    # -- picking and fitting ----------------------------------------------------------------------------------

    def handle_click(self, x: int, y: int, additive: bool) -> bool:
        """While the tool is on, a click fits a facet around the mesh point under it; True: click taken.
        Returns at once: the pick and the fit run on workers, and `fitted` tells when the facet is shown."""
        if not self.action.isChecked() or self.viewer.mesh is None:
            return False
        # the facet on show is not the one clicked for, and a radius changed meanwhile is the fit's to take
        self.point = self.preview = None
        self.accept_button.setEnabled(False)
        self._start(Task("Picking the mesh", pick_mesh, self.viewer.mesh, *self.viewer.view.line_of_sight(x, y)),
                    self._picked)
        self.message.setText("picking the mesh…")
        return True

    def fit(self, point: np.ndarray) -> None:
        """Fit a facet to the faces within the radius of `point` (local frame) on a worker, and show it."""
        self.point = np.asarray(point, dtype=float)
        self.preview = None  # the facet on show was fitted to another point or radius: it cannot be stored
        self.accept_button.setEnabled(False)
        radius = self.radius.value() / length_scale(self.session.similarity())  # given in the readouts' frame
        self.message.setText("fitting the facet…")
        self._start(Task("Fitting a facet", _fit, self.viewer.mesh, self.point, radius), self._show)

    def _start(self, task: Task, done: Callable[[object], None]) -> None:
        if self._task is not None:
            self._task.cancel()  # superseded: whatever it still finds is dropped
        self._task = task
        task.signals.done.connect(done)
        task.signals.failed.connect(self._failed)
        task.signals.cancelled.connect(self._cancelled)
        self.session.jobs.start(task)

    def _current(self) -> bool:
        """Whether the signal being handled comes from the latest task (a superseded one's failure is not)."""
        return self._task is not None and self.sender() is self._task.signals

    def _picked(self, point: np.ndarray | None) -> None:
        if point is None:
            self.message.setText("no mesh under the cursor: click on the rock")
            self.draw()
            self.fitted.emit(None)
        else:
            self.fit(point)

    def _show(self, facet: Facet) -> None:
        self.preview = facet
        verdict = "Accept to store it" if facet.accepted else f"rejected: {facet.rejected_reason}"
        self.message.setText(f"{describe_facet(facet, self.session.similarity())}; {facet.n_points} vertices. "
                             f"{verdict}")
        self.accept_button.setEnabled(facet.accepted)
        self.draw()
        self.fitted.emit(facet)

    def _failed(self, exc: BaseException) -> None:
        if not self._current():
            return
        if isinstance(exc, TracemapError):  # no face that close, or a patch too thin for a plane
            self.message.setText(describe(exc))
        else:
            show_error(self.viewer, "Fitting a facet", exc)
        self.draw()  # the patch of the facet that was on show goes
        self.fitted.emit(None)

    def _cancelled(self) -> None:
        if self._current():  # Cancel pressed in the progress panel, not a newer click
            self.message.setText("cancelled: click an exposed fracture face on the mesh")
            self.draw()

    def _radius_changed(self, radius: float) -> None:
        self.session.set_setting(RADIUS_SETTING, radius)
        if self.point is not None:
            self.fit(self.point)

    def _toggled(self, on: bool) -> None:
        if not on:
            if self._task is not None:
                self._task.cancel()
                self._task = None
            self.point = self.preview = None
            self.accept_button.setEnabled(False)
            self.draw()
        else:
            self.dock.show()
            self.message.setText("Click an exposed fracture face on the mesh")
            self._prepare(self.viewer.mesh)

    def _mesh_loaded(self, mesh: Mesh) -> None:
        self.draw()
        if self.action.isChecked():
            self._prepare(mesh)

    def _prepare(self, mesh: Mesh | None) -> None:
        """Index the mesh on a worker now, so that the first click need not wait for it."""
        if mesh is not None and (self._indexed is None or self._indexed() is not mesh):
            self._indexed = weakref.ref(mesh)
            self.session.jobs.start(Task("Indexing the mesh for facets", _index, mesh))

    # -- drawing ----------------------------------------------------------------------------------------------

    def draw(self) -> None:
        """The stored facets as discs, and the patch and disc of the facet on show."""
        plotter = self.viewer.view.plotter
        for name in (PATCH_ACTOR, PREVIEW_ACTOR, STORED_ACTOR):
            plotter.remove_actor(name)
        if self.viewer.mesh is None:
            return
        shown = []
        if self.facets:
            shown.append(plotter.add_mesh(pv.merge([_disc(f) for f in self.facets]), color=STORED_COLOR,
                                          opacity=DISC_OPACITY, lighting=False, pickable=False, name=STORED_ACTOR))
        if self.preview is not None:
            shown.append(plotter.add_mesh(_patch(self.viewer.mesh, self.preview.faces), color=PATCH_COLOR,
                                          lighting=False, pickable=False, name=PATCH_ACTOR))
            color = ACCEPTED_COLOR if self.preview.accepted else REJECTED_COLOR
            shown.append(plotter.add_mesh(_disc(self.preview), color=color, opacity=PREVIEW_OPACITY, lighting=False,
                                          pickable=False, name=PREVIEW_ACTOR))
        for actor in shown:  # patches and discs lie on the mesh faces: draw them in front, not through them
            actor.GetMapper().SetRelativeCoincidentTopologyPolygonOffsetParameters(0, ON_TOP)
        self.viewer.view.refresh()


def _index(mesh: Mesh, *, progress: Progress) -> None:
    """Build (and cache on the mesh) what picks and fits read, in the order they read it."""
    progress(0.0, "indexing the mesh faces")
    mesh.face_tree, mesh.face_reach, mesh.face_normals, mesh.face_areas  # noqa: B018


def _fit(mesh: Mesh, point: np.ndarray, radius: float, *, progress: Progress) -> Facet:
    progress(0.0, "indexing the mesh faces")
    mesh.face_tree  # noqa: B018 - built (or waited for) first: a fit superseded meanwhile stops at the next report
    progress(0.5, "fitting the facet")
    return fit_mesh_facet(mesh, mesh_patch(mesh, point, radius))


def _disc(facet: Facet) -> pv.PolyData:
    return pv.Disc(center=facet.centroid, inner=0.0, outer=facet.radius, normal=facet.normal, c_res=48)


def _patch(mesh: Mesh, faces: np.ndarray) -> pv.PolyData:
    """The faces of a patch with only their own vertices."""
    used, inverse = np.unique(mesh.faces[faces], return_inverse=True)
    triangles = inverse.reshape(-1, 3)
    return pv.PolyData(mesh.vertices[used], np.column_stack([np.full(len(triangles), 3), triangles]).ravel())
