"""The photo drape dock of the 3D viewer: one photo projected onto the mesh as a texture (the paper's Fig. 5A).

Choosing a photo reads it and works out which faces its camera saw on a worker (`engine.drape.drape_photo`);
the viewer then draws those faces with the photo at full resolution and the others with the mesh colours.
The photo's 2D traces land on the 3D traces made from them, which shows at a glance how faithfully the
extraction followed them. "None" takes the photo off.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import Signal
from PySide6.QtWidgets import QComboBox, QLabel, QVBoxLayout, QWidget

from engine.cameras import Camera
from engine.delineate import read_photo
from engine.drape import Drape, drape_photo
from engine.errors import InputError, Progress, report
from engine.mesh import Mesh
from tracemap_gui.error_dialog import show_error
from tracemap_gui.workers import Task

if TYPE_CHECKING:
    from tracemap_gui.viewer3d import Viewer3D

NONE = "None"


class PhotoDrapePanel(QWidget):
    """A photo box; `drape` is the photo draped now (None for none)."""

    changed = Signal()  # the drape changed: the viewer redraws

    def __init__(self, viewer: Viewer3D):
        super().__init__(viewer)
        self.setObjectName("drape-panel")
        self.viewer = viewer
        self.session = viewer.session
        self.drape: Drape | None = None
        self._task: Task | None = None
        self.photo_box = QComboBox(self)
        self.photo_box.setObjectName("drape-photo")
        self.info = QLabel(self)
        self.info.setObjectName("drape-info")  # short lines, not word wrap: docks do not grow for wrapped labels
        layout = QVBoxLayout(self)
        layout.addWidget(self.photo_box)
        layout.addWidget(self.info)
        layout.addStretch(1)
        self.dock = viewer.add_panel(self, "Photo drape", "drape-dock", group="layers")
        self.photo_box.currentTextChanged.connect(self._choose)
        self.session.opened.connect(self._reload)
        self.session.closed.connect(self._reload)
        viewer.mesh_loaded.connect(lambda _mesh: self._reload())  # a drape belongs to one mesh
        self._reload()

    def _reload(self) -> None:
        """The photos of the open project, none draped."""
        self.photo_box.blockSignals(True)
        self.photo_box.clear()
        self.photo_box.addItems([NONE, *self.session.images()])
        self.photo_box.blockSignals(False)
        self._choose(NONE)

    def _choose(self, name: str) -> None:
        if self._task is not None:
            self._task.cancel()  # its drape, still on the way, is dropped
            self._task = None
        if name in (NONE, ""):
            self._set(None)
            return
        mesh = self.viewer.mesh
        try:
            if mesh is None:
                raise InputError(None, "the mesh is still loading; choose the photo again once it is shown")
            path = self.session.project.image_path(name)
            if path is None:
                raise InputError(None, f"image {name!r} has no photo file in the project")
        except Exception as exc:  # noqa: BLE001 - a moved or changed photo names itself; nothing changes
            self._failed(name, exc)
            return
        task = Task(f"Draping {name}", self._drape_photo, mesh, self.session.camera(name), path,
                    self.viewer.view.max_texture_size())
        task.signals.done.connect(self._set)
        task.signals.failed.connect(lambda exc: self._failed(name, exc))
        self._task = task
        self.info.setText(f"reading {path.name}…")
        self.session.jobs.start(task)

    def _drape_photo(self, mesh: Mesh, camera: Camera, path: Path, max_size: int | None, *,
                     progress: Progress) -> Drape:
        """Runs on a worker: the photo and the session's ray tracer of the mesh."""
        report(progress, 0.0, f"reading {path.name}")
        photo = read_photo(path, camera)
        tracer = self.session.mesh_tracer.of(mesh, progress=lambda f, m: report(progress, 0.2 + 0.1 * f, m))
        return drape_photo(mesh, camera, photo, tracer, max_size=max_size,
                           progress=lambda f, m: report(progress, 0.3 + 0.7 * f, m))

    def _set(self, drape: Drape | None) -> None:
        self._task = None
        self.info.setText("" if drape is None else _describe(drape))
        if drape is self.drape:
            return
        self.drape = drape
        if not self.session.is_open:  # a closed project's scene is cleared, not redrawn
            return
        if drape is not None and drape.scale < 1.0:
            self.viewer.statusBar().showMessage(f"{drape.image} reduced to {_size(drape)} px: the graphics card "
                                                "takes no larger texture", 10000)
        self.changed.emit()

    def _failed(self, name: str, exc: BaseException) -> None:
        self._task = None
        show_error(self, f"Draping {name}", exc)
        self.photo_box.setCurrentText(NONE)


def _size(drape: Drape) -> str:
    h, w = drape.texture.shape[:2]
    return f"{w}×{h}"


def _describe(drape: Drape) -> str:
    text = f"{drape.image} on {drape.seen.sum():,} of {len(drape.seen):,} faces ({drape.seen.mean():.0%})"
    if drape.scale < 1.0:
        text += f"\ntexture reduced to {_size(drape)} px (the graphics card's limit)"
    return text
