"""File → Export results…: `tracemap export` from the application (the tables, PLY, GeoPackage, VTP).

The export reads the project on a worker through a handle of its own (`Project.for_thread`), so a long one
(a mesh's intensity maps as PLY) leaves the windows free; it writes all or nothing into the folder
(`engine.io.export_tables`). The folder and formats chosen last are kept with the project.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from PySide6.QtWidgets import QCheckBox, QHBoxLayout, QWidget

from engine.errors import InputError
from engine.io import EXPORT_FORMATS, SUMMARY_SECTION, export_tables
from engine.project import Project
from tracemap_gui.new_project import PathField
from tracemap_gui.value_dialog import ValueDialog

FORMAT_TIPS = {"csv": "traces.csv, trace_vertices.csv, traces2d.csv, sets.csv, planes.csv, summary.json, …",
               "ply": "connectivity.ply and, after intensity maps, intensity.ply (CloudCompare, MeshLab)",
               "gpkg": "traces.gpkg: LINESTRING Z traces, scanlines, scan circles (QGIS, GDAL)",
               "vtp": "traces.vtp, scanlines.vtp, scan_circles.vtp (ParaView)"}


@dataclass(frozen=True)
class ExportRequest:
    folder: Path
    formats: tuple[str, ...]


@dataclass(frozen=True)
class Exported:
    """What an export wrote, and the stored results older than the traces (summary.json's out_of_date)."""

    folder: Path
    files: tuple[Path, ...]
    stale: tuple[str, ...]

    def describe(self) -> str:
        line = f"wrote {len(self.files)} files to {self.folder}"
        if self.stale:
            sections = ", ".join(dict.fromkeys(SUMMARY_SECTION[n] for n in self.stale))
            line += f"; {sections} computed before the traces last changed: analyse again"
        return line


def export_results(project: Project, request: ExportRequest, *, progress) -> Exported:
    """Write the export on this (worker) thread through its own handle on the open project."""
    progress(0.0, f"exporting to {request.folder}")
    own = project.for_thread()
    try:
        files = export_tables(own, request.folder, request.formats)
        return Exported(request.folder, tuple(files), tuple(own.stale_results()))
    finally:
        own.close()


class ExportDialog(ValueDialog):
    """The folder and the formats; `values` is an `ExportRequest` once accepted."""

    def __init__(self, folder: str = "", formats: tuple[str, ...] = ("csv", "ply"), parent: QWidget | None = None):
        super().__init__("Export results", "export-dialog", parent)
        self.folder = PathField("export-folder", {"Folder…": "folder"}, parent=self)
        self.folder.edit.setText(folder)
        boxes = QWidget(self)
        row = QHBoxLayout(boxes)
        row.setContentsMargins(0, 0, 0, 0)
        self.formats = {}
        for name in EXPORT_FORMATS:
            box = QCheckBox(name, boxes)
            box.setObjectName(f"export-{name}")
            box.setChecked(name in formats)
            box.setToolTip(FORMAT_TIPS[name])
            row.addWidget(box)
            self.formats[name] = box
        self.add_row("Folder", self.folder)
        self.add_row("Formats", boxes)

    def parse(self) -> ExportRequest:
        if not self.folder.text:
            raise InputError(None, "Folder: expected where to write the files; none given")
        folder = Path(self.folder.text).expanduser()
        if folder.exists() and not folder.is_dir():
            raise InputError(folder, "Folder: is a file; expected a folder (made if it does not exist)")
        formats = tuple(name for name, box in self.formats.items() if box.isChecked())
        if not formats:
            raise InputError(None, "Formats: expected at least one of " + ", ".join(EXPORT_FORMATS))
        return ExportRequest(folder, formats)
