"""Ground-control points in the image editor: the GCP tool picks them on the photos, a dock lists them and
registers the model to their world coordinates (Horn 1987, MATHS §11; `engine.register`).

A click with the GCP tool asks for the point's name and world X, Y, Z (or an existing name, to add this
photo's observation of it); each pick is one undoable edit. Register ray-traces every GCP's pixels onto the
mesh on a worker, fits the similarity and stores it (undoable), then shows each GCP's residual (m) and the
RMS error; exports are written in the GCPs' frame from then on.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PySide6.QtCore import QPointF, Qt
from PySide6.QtGui import QColor, QMouseEvent, QPainter
from PySide6.QtWidgets import (QComboBox, QDockWidget, QHBoxLayout,
                               QHeaderView, QLabel, QLineEdit, QPushButton, QTreeWidget, QTreeWidgetItem, QVBoxLayout,
                               QWidget)

from engine.cameras import Camera
from engine.errors import InputError, TracemapError
from engine.register import Registration, register_gcps
from tracemap_gui import tools
from tracemap_gui.commands import ProjectCommand
from tracemap_gui.error_dialog import show_error
from tracemap_gui.mesh_tracer import MeshTracer
from tracemap_gui.photo_view import PhotoView
from tracemap_gui.trace_layer import cosmetic_pen
from tracemap_gui.value_dialog import ValueDialog
from tracemap_gui.workers import Task

if TYPE_CHECKING:
    from sqlite3 import Connection

    from engine.project import Project
    from tracemap_gui.session import Session

MARK = QColor(0, 230, 255)
MARK_SIZE = 9  # screen pixels, half the cross


class GcpCommand(ProjectCommand):
    """Replace one GCP's entry ({"world", "observations"}, or None for no GCP of that name) as one edit;
    `changed` runs after every do and undo so the dock shows what the project holds."""

    def __init__(self, session: Session, name: str, before: dict | None, after: dict | None, text: str,
                 changed: Callable[[], None]):
        super().__init__(session, text)
        self.name, self.before, self.after, self._changed = name, before, after, changed

    def _do(self, project: Project, db: Connection) -> list:
        self._put(project, db, self.after)
        return []

    def _undo(self, project: Project, db: Connection) -> list:
        self._put(project, db, self.before)
        return []

    def _put(self, project: Project, db: Connection, entry: dict | None) -> None:
        if entry is None:
            project.remove_gcp(self.name, db)
        else:
            project.set_gcp(self.name, entry["world"], entry["observations"], db)

    def _store(self, step: Callable[[Project, Connection], list]) -> None:
        super()._store(step)
        self._changed()


class RegistrationCommand(ProjectCommand):
    """Store a new registration (undo brings back the one before, or none)."""

    def __init__(self, session: Session, after: Registration, changed: Callable[[], None]):
        super().__init__(session, f"Register with {len(after.names)} GCPs")
        self.before, self.after, self._changed = session.project.registration(), after, changed

    def _do(self, project: Project, db: Connection) -> list:
        project.set_registration(self.after, db)
        return []

    def _undo(self, project: Project, db: Connection) -> list:
        project.set_registration(self.before, db)
        return []

    def _store(self, step: Callable[[Project, Connection], list]) -> None:
        super()._store(step)
        self._changed()
        self._session.registration_changed.emit()


def compute_registration(mesh_path: Path, origin: np.ndarray, cameras: dict[str, Camera], gcps: dict[str, dict],
                         tracers: MeshTracer, *, progress: Callable[[float, str], None]) -> Registration:
    """Ray-trace the GCPs' pixels on the session's ray tracer of the mesh and fit the similarity (runs in a
    `workers.Task`)."""
    tracer = tracers.tracer(mesh_path, origin, progress=lambda f, m: progress(0.8 * f, m))
    progress(0.8, "ray tracing the GCPs")
    return register_gcps(gcps, cameras, tracer, origin)


def parse_world(texts: tuple[str, str, str]) -> list[float]:
    """World X, Y, Z typed as text (metres); InputError naming the field that is not a finite number."""
    values = []
    for label, text in zip("XYZ", texts):
        try:
            value = float(text.strip())
        except ValueError:
            raise InputError(None, f"{label} {text.strip()!r}: expected a number of metres") from None
        if not np.isfinite(value):
            raise InputError(None, f"{label} {text.strip()!r}: expected a finite number of metres")
        values.append(value)
    return values


class GcpDialog(ValueDialog):
    """Name and world X, Y, Z of the GCP just clicked; choosing an existing name fills in its coordinates."""

    def __init__(self, gcps: dict[str, dict], image: str, pixel: np.ndarray, parent: QWidget | None = None):
        super().__init__(f"GCP on {image} at ({pixel[0]:.1f}, {pixel[1]:.1f})", "gcp-dialog", parent)
        self._gcps = gcps
        self.image, self.pixel = image, pixel
        self.name = QComboBox(self)
        self.name.setEditable(True)
        self.name.addItems(sorted(gcps))
        self.name.setCurrentText(_next_name(gcps))
        self.coordinates = [QLineEdit(self) for _ in range(3)]
        self.add_row("Name", self.name)
        for label, edit in zip("XYZ", self.coordinates):
            self.add_row(f"World {label} (m)", edit)
        self.name.currentTextChanged.connect(self._fill)

    def _fill(self, name: str) -> None:
        if name in self._gcps:
            for edit, value in zip(self.coordinates, self._gcps[name]["world"]):
                edit.setText(f"{value:.4f}")

    def parse(self) -> tuple[str, list[float]]:
        name = self.name.currentText().strip()
        if not name:
            raise InputError(None, "the GCP needs a name")
        return name, parse_world(tuple(e.text() for e in self.coordinates))


def _next_name(gcps: dict[str, dict]) -> str:
    k = len(gcps) + 1
    while f"GCP{k}" in gcps:
        k += 1
    return f"GCP{k}"


class GcpPanel(QDockWidget):
    """The project's GCPs with their observations, the Register button and the residuals it found."""

    def __init__(self, session: Session, parent: QWidget | None = None):
        super().__init__("Ground control", parent)
        self.setObjectName("gcp-dock")
        self.session = session
        self.gcps: dict[str, dict] = {}
        self.tree = QTreeWidget(self)
        self.tree.setObjectName("gcp-tree")
        self.tree.setHeaderLabels(["GCP / photo", "residual (m)", "X / u", "Y / v", "Z"])
        self.tree.header().setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        self.summary = QLabel(self)
        self.summary.setObjectName("gcp-summary")
        self.summary.setWordWrap(True)
        self.remove_button = QPushButton("Remove", self)
        self.remove_button.setObjectName("gcp-remove")
        self.remove_button.clicked.connect(self.remove_selected)
        self.register_button = QPushButton("Register", self)
        self.register_button.setObjectName("gcp-register")
        self.register_button.setToolTip("fit the model → world similarity to the GCPs (at least 3, not on a line)")
        self.register_button.clicked.connect(self.register)
        buttons = QHBoxLayout()
        buttons.addWidget(self.remove_button)
        buttons.addWidget(self.register_button)
        body = QWidget(self)
        layout = QVBoxLayout(body)
        layout.addWidget(self.tree)
        layout.addWidget(self.summary)
        layout.addLayout(buttons)
        self.setWidget(body)
        self._task: Task | None = None
        session.opened.connect(self.refresh)
        session.closed.connect(self.refresh)
        self.refresh()

    # -- showing ----------------------------------------------------------------------------------------------

    def refresh(self) -> None:
        """Read the GCPs and the registration from the project and show them."""
        self.gcps = self.session.project.gcps() if self.session.is_open else {}
        registration = self.session.project.registration() if self.session.is_open else None
        errors = {} if registration is None else dict(zip(registration.names, registration.similarity.errors))
        self.tree.clear()
        for name, gcp in self.gcps.items():
            error = f"{errors[name]:.4f}" if name in errors else ""
            item = QTreeWidgetItem(self.tree, [name, error, *(f"{x:.3f}" for x in gcp["world"])])
            for image, (u, v) in sorted(gcp["observations"].items()):
                QTreeWidgetItem(item, [image, "", f"{u:.1f}", f"{v:.1f}"])
        self.tree.expandAll()
        self.summary.setText(self._describe(registration))

    def _describe(self, registration: Registration | None) -> str:
        if registration is None:
            return f"{len(self.gcps)} GCPs; not registered (at least 3 GCPs off one line are needed)"
        sim = registration.similarity
        stale = "" if self._current(registration) else " The GCPs changed since: press Register again."
        return (f"Registered with {len(registration.names)} GCPs: RMS error {sim.rmse:.4f} m, scale "
                f"{sim.scale:.6f}.{stale}")

    def _current(self, registration: Registration) -> bool:
        """Whether the registration was made from the GCPs as they are now."""
        if set(registration.names) != set(self.gcps):
            return False
        world = np.array([self.gcps[n]["world"] for n in registration.names])
        observed = all(set(self.gcps[n]["observations"]) == set(i) for n, i in zip(registration.names,
                                                                                   registration.images))
        return observed and np.allclose(world, registration.world, rtol=0, atol=1e-9)

    # -- editing ----------------------------------------------------------------------------------------------

    def pick(self, image: str, pixel: np.ndarray, name: str, world: list[float]) -> None:
        """Store an observation of GCP `name` (new, or with new world coordinates) on `image` at `pixel`."""
        before = self.gcps.get(name)
        observations = dict(before["observations"]) if before else {}
        observations[image] = [float(pixel[0]), float(pixel[1])]
        after = {"world": world, "observations": observations}
        self._push(GcpCommand(self.session, name, before, after, f"Pick GCP {name} on {image}", self.refresh))

    def remove_selected(self) -> None:
        """Remove the selected GCP, or only the selected observation of it."""
        item = self.tree.currentItem()
        if item is None:
            return
        parent = item.parent()
        name = (parent or item).text(0)
        before = self.gcps[name]
        if parent is None or len(before["observations"]) == 1:
            after, text = None, f"Remove GCP {name}"
        else:
            kept = {k: v for k, v in before["observations"].items() if k != item.text(0)}
            after, text = {"world": before["world"], "observations": kept}, f"Remove GCP {name} on {item.text(0)}"
        self._push(GcpCommand(self.session, name, before, after, text, self.refresh))

    def register(self) -> None:
        """Fit the registration on a worker; it is stored (undoably) and shown when it arrives."""
        if self._task is not None or not self.session.is_open:
            return
        try:
            mesh_path = self.session.project.mesh_path
        except TracemapError as exc:
            show_error(self, "Registration", exc)
            return
        task = Task("Registering", compute_registration, mesh_path, self.session.project.origin,
                    self.session.cameras(), self.gcps, self.session.mesh_tracer)
        task.signals.done.connect(lambda reg: self._push(RegistrationCommand(self.session, reg, self.refresh)))
        task.signals.failed.connect(lambda exc: show_error(self, "Registration", exc))
        task.signals.ended.connect(self._ended)
        self.register_button.setEnabled(False)
        self._task = self.session.jobs.start(task)

    def _ended(self) -> None:
        self._task = None
        self.register_button.setEnabled(True)

    def _push(self, command: ProjectCommand) -> None:
        try:
            self.session.push(command)
        except Exception as exc:  # noqa: BLE001 - shown to the user; the transaction rolled back
            show_error(self, command.text(), exc)


class GcpTool(tools.Tool):
    """Click a ground-control point on the photo; a dialog asks its name and world X, Y, Z."""

    name = "GCP"
    hint = "Click a ground-control point: name it and give its world X, Y, Z (or pick a name already used)"

    def __init__(self, session: Session, view: PhotoView, panel: GcpPanel):
        super().__init__(session, view)
        self.panel = panel
        self.dialog: GcpDialog | None = None

    def press(self, pos: QPointF, event: QMouseEvent) -> None:
        if event.button() != Qt.MouseButton.LeftButton:
            return
        image, pixel = self.view.image, self.inside(pos)
        dialog = self.dialog = GcpDialog(self.panel.gcps, image, pixel, self.view.window())
        dialog.accepted.connect(lambda: self._picked(image, pixel, *dialog.values))
        dialog.open()  # window-modal, not a nested event loop

    def _picked(self, image: str, pixel: np.ndarray, name: str, world: list[float]) -> None:
        self.panel.pick(image, pixel, name, world)
        self.view.viewport().update()  # the new mark

    def paint(self, painter: QPainter, view: PhotoView) -> None:
        """A cross and the name at each GCP picked on this photo."""
        painter.setPen(cosmetic_pen(MARK, 2))
        for name, gcp in self.panel.gcps.items():
            uv = gcp["observations"].get(view.image)
            if uv is None:
                continue
            p = self.screen(np.array([uv]))[0]
            painter.drawLine(QPointF(p.x() - MARK_SIZE, p.y()), QPointF(p.x() + MARK_SIZE, p.y()))
            painter.drawLine(QPointF(p.x(), p.y() - MARK_SIZE), QPointF(p.x(), p.y() + MARK_SIZE))
            painter.drawText(QPointF(p.x() + MARK_SIZE + 2, p.y() - 2), name)
