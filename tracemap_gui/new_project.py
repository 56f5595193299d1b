"""File → New project…: `tracemap new` as a form (the mesh, the camera file or COLMAP folder, the photos).

The form checks what it can at once (the files exist, the camera file's format, the project's name is
free); reading the cameras, matching the photos and checking that the cameras see the mesh take seconds
on a big mesh, so the application runs `engine.project.new_project` on a worker and opens the project when
it is made. Nothing is written when any of it fails.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from PySide6.QtWidgets import QFileDialog, QHBoxLayout, QLineEdit, QPushButton, QSpinBox, QWidget

from engine.errors import InputError
from engine.cameras.detect import detect_format
from engine.project import SIZELESS_FORMATS, SUFFIX, new_project
from tracemap_gui.value_dialog import ValueDialog

MESH_FILTER = "meshes (*.ply *.obj *.stl *.off *.glb *.gltf);;all files (*)"
CAMERA_FILTER = ("camera files (*.xml *.out *.nvm *.json *.mvs *.txt *.bin);;all files (*)")


@dataclass(frozen=True)
class NewProject:
    """What the form asks for: paths as given; image_size (width, height) or None."""

    path: Path
    mesh: Path
    cameras: Path
    images: Path | None = None
    image_list: Path | None = None
    image_size: tuple[int, int] | None = None


def create_project(request: NewProject, *, progress) -> Path:
    """Make the project (on a worker) and close it again: the application opens it in its windows."""
    progress(0.0, "reading the cameras and the mesh")
    with new_project(request.path, request.mesh, request.cameras, images=request.images,
                     image_list=request.image_list, image_size=request.image_size) as project:
        return project.path


class PathField(QWidget):
    """A path typed or chosen with buttons (a file to open, a folder, or a file to save)."""

    def __init__(self, name: str, buttons: dict[str, str], file_filter: str = "", parent: QWidget | None = None):
        super().__init__(parent)
        self.edit = QLineEdit(self)
        self.edit.setObjectName(name)
        self.edit.setMinimumWidth(360)
        layout = QHBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self.edit)
        for text, kind in buttons.items():
            button = QPushButton(text, self)
            button.clicked.connect(lambda _=False, k=kind: self._choose(k, file_filter))
            layout.addWidget(button)

    def _choose(self, kind: str, file_filter: str) -> None:
        start = self.edit.text()
        if kind == "folder":
            path = QFileDialog.getExistingDirectory(self, "Choose a folder", start)
        elif kind == "save":
            path, _ = QFileDialog.getSaveFileName(self, "Save the project as", start, f"tracemap projects (*{SUFFIX})")
        else:
            path, _ = QFileDialog.getOpenFileName(self, "Choose a file", start, file_filter)
        if path:
            self.edit.setText(path)

    @property
    def text(self) -> str:
        return self.edit.text().strip()


class NewProjectDialog(ValueDialog):
    """The form of File → New project…; `values` is a `NewProject` once accepted."""

    def __init__(self, parent: QWidget | None = None):
        super().__init__("New project", "new-project-dialog", parent)
        self.mesh = PathField("new-project-mesh", {"File…": "file"}, MESH_FILTER, self)
        self.cameras = PathField("new-project-cameras", {"File…": "file", "Folder…": "folder"}, CAMERA_FILTER, self)
        self.images = PathField("new-project-images", {"Folder…": "folder"}, parent=self)
        self.image_list = PathField("new-project-image-list", {"File…": "file"}, "lists (*.txt);;all files (*)", self)
        self.width_box, self.height_box = (self._size_box(name) for name in ("new-project-width", "new-project-height"))
        size = QWidget(self)
        row = QHBoxLayout(size)
        row.setContentsMargins(0, 0, 0, 0)
        row.addWidget(self.width_box)
        row.addWidget(self.height_box)
        self.project = PathField("new-project-path", {"Save as…": "save"}, parent=self)
        self.mesh.edit.editingFinished.connect(self._suggest_name)
        self.add_row("Mesh", self.mesh)
        self.add_row("Cameras (file or COLMAP folder)", self.cameras)
        self.add_row("Photos folder (optional)", self.images)
        self.add_row("Bundler image list (optional)", self.image_list)
        size.setToolTip("only for Bundler, NVM and OpenMVS files, which do not store the photos' size, when the "
                        "photos are not at hand")
        self.add_row("Photo size (W × H)", size)
        self.add_row("Project file", self.project)

    def _size_box(self, name: str) -> QSpinBox:
        box = QSpinBox(self)
        box.setObjectName(name)
        box.setRange(0, 100_000)
        box.setSpecialValueText("from the photos")
        return box

    def _suggest_name(self) -> None:
        """A project beside the mesh, named after it, until the user names one."""
        if self.mesh.text and not self.project.text:
            self.project.edit.setText(str(Path(self.mesh.text).with_suffix(SUFFIX)))

    def parse(self) -> NewProject:
        mesh = _existing(self.mesh.text, "Mesh", "a mesh file (PLY, OBJ, STL, OFF, glTF)")
        cameras = _existing(self.cameras.text, "Cameras", "a camera file or a COLMAP model folder", folder=None)
        images = _existing(self.images.text, "Photos folder", "a folder", folder=True) if self.images.text else None
        image_list = _existing(self.image_list.text, "Bundler image list", "a file") if self.image_list.text else None
        kind = detect_format(cameras)  # from the file's first bytes: a wrong file is said here, not after seconds
        size = (self.width_box.value(), self.height_box.value())
        if (0 in size) != (size == (0, 0)):
            raise InputError(None, "Photo size: expected both the width and the height, or neither")
        if size != (0, 0) and kind not in SIZELESS_FORMATS:
            raise InputError(cameras, f"Photo size: a {kind} file gives the size of every photo; leave it empty")
        return NewProject(_project_path(self.project.text), mesh, cameras, images, image_list,
                          None if size == (0, 0) else size)


def _existing(text: str, field: str, expected: str, *, folder: bool | None = False) -> Path:
    """The path in a field, checked to exist (a folder if `folder`, a file if False, either if None)."""
    if not text:
        raise InputError(None, f"{field}: expected {expected}; none given")
    path = Path(text).expanduser()
    found = path.is_dir() if folder else path.is_file() if folder is False else path.exists()
    if not found:
        raise InputError(path, f"{field}: no such {'folder' if folder else 'file'}; expected {expected}")
    return path


def _project_path(text: str) -> Path:
    if not text:
        raise InputError(None, "Project file: expected where to save the project; none given")
    path = Path(text).expanduser()
    path = path if path.suffix == SUFFIX else path.with_name(path.name + SUFFIX)
    if path.exists():
        raise InputError(path, "Project file: a file of that name exists; choose another name")
    if not path.parent.is_dir():
        raise InputError(path, f"Project file: the folder {path.parent} does not exist")
    return path
