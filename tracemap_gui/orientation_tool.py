"""Manual orientation in the 3D viewer: the selected trace's plane as a disc, its candidate poles as a ring.

A trace's plane contains its end-node axis a, so its candidate poles lie on the great circle ⟂ a (Seers &
Hodgetts 2016 §3.4; MATHS §1.2). The ring draws that circle in 3D about the trace's centroid c: the ring point
p stands for the pole (p − c)/r, so the disc of the plane with that pole contains the axis. With the
"Set orientation" tool on, a click on the ring sets the pole there (`engine.orientation.manual_orientation`)
as one undoable command; "Type orientation…" takes a dip and dip direction instead.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pyvista as pv
from PySide6.QtCore import QObject
from PySide6.QtGui import QAction, QKeySequence
from PySide6.QtWidgets import QLineEdit, QToolBar, QWidget

from engine.errors import InputError, TracemapError
from engine.orientation import (
    axial_angle,
    candidate_circle,
    dip_dipdir_to_normal,
    eigen_orientation,
    manual_orientation,
    normal_to_dip_dipdir,
)
from engine.register import Similarity, model_directions, rotate_directions
from engine.render import METHOD_COLORS, trace_colors
from engine.traces import Trace3D
from tracemap_gui.commands import EditTraces3D
from tracemap_gui.error_dialog import show_error
from tracemap_gui.scene_view import display_coordinates
from tracemap_gui.value_dialog import ValueDialog

if TYPE_CHECKING:
    from tracemap_gui.viewer3d import Viewer3D

RING_SEGMENTS = 360  # 1° per segment: a click between vertices is interpolated along the segment
PICK_PX = 6  # how near the ring (display pixels) a click must fall
RING_SCALE = 1.3  # ring radius / disc radius: the ring stays visible around the disc
DISC_OPACITY = 0.35
ON_TOP = -66000  # VTK coincident-topology offset units that draw lines and points in front of the mesh
CURRENT_COLOR = (255, 0, 255)  # the selection colour of the traces
RING_COLOR = (20, 20, 20)
ACTORS = ("orientation-disc", "orientation-ring", "orientation-current", "orientation-solutions")


@dataclass(frozen=True)
class Glyph:
    """Where a trace's disc and ring go: centroid, end-node axis and the circle's basis (e1 = eigen pole
    projected onto it, e2 = axis × e1, as in `engine.orientation.candidate_circle`), radii in metres, and
    the current pole (None while the trace has none)."""

    centroid: np.ndarray
    axis: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    disc_radius: float
    normal: np.ndarray | None

    @property
    def ring_radius(self) -> float:
        return RING_SCALE * self.disc_radius

    def pole_at(self, phi: float) -> np.ndarray:
        """The candidate pole at angle φ (radians) along the ring from e1."""
        return np.cos(phi) * self.e1 + np.sin(phi) * self.e2

    def angle_of(self, pole: np.ndarray) -> float:
        """Angle (radians) on the ring of a pole's projection onto the circle."""
        return float(np.arctan2(pole @ self.e2, pole @ self.e1))

    def ring_points(self, n: int = RING_SEGMENTS) -> np.ndarray:
        """(n, 3) vertices of the ring, vertex k at φ = 2πk/n."""
        phi = 2 * np.pi * np.arange(n) / n
        return self.centroid + self.ring_radius * (np.cos(phi)[:, None] * self.e1 + np.sin(phi)[:, None] * self.e2)


def glyph_of(trace: Trace3D) -> Glyph:
    """The disc and ring of a trace; InputError when it has < 3 vertices or coincident end nodes."""
    fit = eigen_orientation(trace.points)
    axis, e1, e2 = candidate_circle(trace.points, fit.normal)
    return Glyph(fit.centroid, axis, e1, e2, 0.5 * trace.chord_length,
                 None if trace.normal is None else np.asarray(trace.normal, dtype=float))


def ring_angle_at(ring_display: np.ndarray, x: float, y: float, tolerance: float = PICK_PX) -> float | None:
    """Angle (radians) of the point of a closed ring polyline (N, 2; vertex k at 2πk/N) nearest (x, y),
    interpolated along its segment, or None when the ring passes farther than `tolerance` pixels away."""
    a = ring_display
    b = np.roll(a, -1, axis=0)
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(((x - a[:, 0]) * d[:, 0] + (y - a[:, 1]) * d[:, 1]) / (d**2).sum(axis=1), 0.0, 1.0)
    t = np.nan_to_num(t)
    dist = np.hypot(a[:, 0] + t * d[:, 0] - x, a[:, 1] + t * d[:, 1] - y)
    if not np.isfinite(dist).any() or np.nanmin(dist) > tolerance:
        return None
    k = int(np.nanargmin(dist))
    return 2 * np.pi * (k + t[k]) / len(a)


def parse_dip_dipdir(dip_text: str, dipdir_text: str) -> tuple[float, float]:
    """Dip in [0, 90] and dip direction in [0, 360] (360 is north, stored as 0) typed as text, in degrees."""
    values = []
    for label, text, top in (("dip", dip_text, 90.0), ("dip direction", dipdir_text, 360.0)):
        try:
            value = float(text.strip().rstrip("°"))
        except ValueError:
            raise InputError(None, f"{label} {text.strip()!r}: expected a number of degrees") from None
        if not 0.0 <= value <= top:
            raise InputError(None, f"{label} {value:g}: expected 0 to {top:g} degrees")
        values.append(value)
    return values[0], values[1] % 360.0


class OrientationDialog(ValueDialog):
    """Dip and dip direction for one trace."""

    def __init__(self, trace: Trace3D, similarity: Similarity | None = None, parent: QWidget | None = None):
        super().__init__(f"Orientation of trace {trace.id}", "orientation-dialog", parent)
        self.trace_id = trace.id
        dip, dipdir = (normal_to_dip_dipdir(rotate_directions(trace.normal, similarity)) if trace.normal is not None
                       else (0.0, 0.0))
        self.dip = QLineEdit(f"{float(dip):.1f}", self)
        self.dipdir = QLineEdit(f"{float(dipdir):.1f}", self)
        self.add_row("Dip (0–90°)", self.dip)
        self.add_row("Dip direction (0–360°)", self.dipdir)

    def parse(self) -> tuple[float, float]:
        return parse_dip_dipdir(self.dip.text(), self.dipdir.text())


class OrientationTool(QObject):
    """The disc and candidate ring of the one selected trace, and the two ways to set its pole by hand."""

    def __init__(self, viewer: Viewer3D) -> None:
        super().__init__(viewer)
        self.viewer = viewer
        self.session = viewer.session
        self.glyph: Glyph | None = None
        self.trace: Trace3D | None = None
        self.dialog: OrientationDialog | None = None
        self._ring = np.zeros((0, 3))
        self.action = QAction("Set orientation", viewer)
        self.action.setCheckable(True)
        self.action.setShortcut(QKeySequence("O"))
        self.action.setStatusTip("Click the ring of candidate poles of the selected trace to set its plane")
        self.action.toggled.connect(self._toggled)
        self.type_action = QAction("Type orientation…", viewer)
        self.type_action.setShortcut(QKeySequence("Shift+O"))
        self.type_action.triggered.connect(self.open_dialog)
        viewer.findChild(QToolBar, "viewer3d-toolbar").addActions([self.action, self.type_action])
        viewer.menuBar().addMenu("&Orientation").addActions([self.action, self.type_action])
        self.session.selection_changed.connect(self.redraw)
        self.session.traces3d_changed.connect(self.redraw)
        self.session.closed.connect(self.redraw)
        viewer.color_box.currentTextChanged.connect(self.redraw)

    # -- drawing ----------------------------------------------------------------------------------------------

    def redraw(self) -> None:
        """Draw the glyph of the one selected trace, or remove it when none or several are selected."""
        had = self.glyph is not None
        self.trace, self.glyph = self._selected(), None
        if self.trace is not None:
            try:
                self.glyph = glyph_of(self.trace)
            except TracemapError as exc:  # too few vertices, or a closed loop: no circle to offer
                self.viewer.statusBar().showMessage(f"no candidate circle: {exc}", 5000)
        plotter = self.viewer.view.plotter
        for name in ACTORS:
            plotter.remove_actor(name, render=False)  # one render at the end, not one per actor
        if self.glyph is not None:
            self._draw(plotter, self.trace, self.glyph)
        if had or self.glyph is not None:
            self.viewer.view.refresh()

    def _selected(self) -> Trace3D | None:
        if not self.session.is_open or len(self.session.selected3d) != 1:
            return None
        (wanted,) = self.session.selected3d
        return next((t for t in self.session.traces3d() if t.id == wanted), None)

    def _draw(self, plotter: pv.Plotter, trace: Trace3D, glyph: Glyph) -> None:
        self._ring = glyph.ring_points()
        ring = pv.PolyData(self._ring, lines=np.r_[len(self._ring) + 1, np.arange(len(self._ring)), 0])
        actor = plotter.add_mesh(ring, color=RING_COLOR, line_width=3, lighting=False, pickable=False,
                                 name=ACTORS[1], render=False)
        actor.GetMapper().SetRelativeCoincidentTopologyLineOffsetParameters(0, ON_TOP)
        if glyph.normal is not None:
            scheme = "method" if self.viewer.style.color_by == "method" else "set"
            disc = pv.Disc(center=glyph.centroid, inner=0.0, outer=glyph.disc_radius, normal=glyph.normal, c_res=72)
            plotter.add_mesh(disc, color=tuple(int(c) for c in trace_colors([trace], scheme)[0]),
                             opacity=DISC_OPACITY, lighting=False, pickable=False, name=ACTORS[0],
                             render=False)
            self._marks(plotter, ACTORS[2], [glyph.normal], [CURRENT_COLOR], 20)
        solutions = [(glyph.e1, METHOD_COLORS["eigen"])]  # φ = 0: the eigen pole projected onto the circle
        if trace.method == "probabilistic" and glyph.normal is not None:
            solutions.append((glyph.normal, METHOD_COLORS["probabilistic"]))
        self._marks(plotter, ACTORS[3], *zip(*solutions), 11)

    def _marks(self, plotter: pv.Plotter, name: str, poles, colors, size: float) -> None:
        """Spheres where poles project onto the ring, at both antipodes (a pole is an axis)."""
        glyph = self.glyph
        phi = np.array([glyph.angle_of(p) for p in poles])
        phi = np.concatenate([phi, phi + np.pi])
        points = glyph.centroid + glyph.ring_radius * np.array([glyph.pole_at(f) for f in phi])
        cloud = pv.PolyData(points)
        cloud.point_data["rgb"] = np.array([*colors, *colors], np.uint8)
        actor = plotter.add_mesh(cloud, scalars="rgb", rgb=True, point_size=size, render_points_as_spheres=True,
                                 pickable=False, name=name, render=False)
        actor.GetMapper().SetRelativeCoincidentTopologyPointOffsetParameter(ON_TOP)

    # -- setting the pole -------------------------------------------------------------------------------------

    def handle_click(self, x: int, y: int, additive: bool) -> bool:
        """While the tool is on, a plain click on the ring sets the pole there; True when it took the click."""
        if not self.action.isChecked() or self.glyph is None or additive:
            return False
        phi = ring_angle_at(display_coordinates(self.viewer.view.plotter.renderer, self._ring), x, y)
        if phi is None:
            return False
        self.set_pole(self.trace, self.glyph.pole_at(phi))
        return True

    def set_pole(self, trace: Trace3D, pole: np.ndarray) -> Trace3D | None:
        """Give `trace` the candidate pole nearest `pole` as one undoable edit; the edited trace, or None."""
        after = copy.deepcopy(trace)  # manual_orientation edits `extra` in place: the command keeps `trace`
        try:
            manual_orientation(after, pole=pole)
            self.session.push(EditTraces3D(self.session, [trace], [after], f"Set orientation of trace {trace.id}"))
        except Exception as exc:  # noqa: BLE001 - shown to the user; nothing was stored
            show_error(self.viewer, "Setting the orientation", exc)
            return None
        dip, dipdir = normal_to_dip_dipdir(rotate_directions(after.normal, self.session.similarity()))
        self.viewer.statusBar().showMessage(f"trace {trace.id}: {float(dip):.1f}° / {float(dipdir):05.1f}°", 5000)
        return after

    def open_dialog(self) -> None:
        """Ask for a dip and dip direction for the one selected trace (non-blocking; OK applies it)."""
        if self.trace is None:
            self.viewer.statusBar().showMessage("select one trace first", 3000)
            return
        dialog = self.dialog = OrientationDialog(self.trace, self.session.similarity(), self.viewer)
        dialog.accepted.connect(lambda: self._typed(dialog))
        dialog.open()

    def _typed(self, dialog: OrientationDialog) -> None:
        trace = next((t for t in self.session.traces3d() if t.id == dialog.trace_id), None)
        if trace is None:  # deleted while the dialog was open
            self.viewer.statusBar().showMessage(f"trace {dialog.trace_id} no longer exists", 5000)
            return
        similarity = self.session.similarity()  # typed in the frame it is shown in
        wanted = model_directions(dip_dipdir_to_normal(*dialog.values), similarity)
        after = self.set_pole(trace, wanted)
        off = 0.0 if after is None else float(axial_angle(wanted, after.normal))
        if off > 0.5:  # the plane must contain the end-node axis: say how far the typed one was moved
            dip, dipdir = normal_to_dip_dipdir(rotate_directions(after.normal, similarity))
            self.viewer.statusBar().showMessage(
                f"trace {after.id}: the typed plane does not contain the end-node axis; stored the nearest "
                f"candidate {float(dip):.1f}° / {float(dipdir):05.1f}° ({off:.1f}° away)", 10000)

    def _toggled(self, on: bool) -> None:
        if on:
            self.viewer.statusBar().showMessage(
                "Set orientation: select one trace, then click its ring of candidate poles", 5000)
