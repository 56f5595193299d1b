"""What the 3D viewer's sampling tools share (the Scanline and Scan circle tools): samples of the rock stored
in the project, measured on a worker against the traces as they are, listed with their readouts, removable,
each edit undoable.

A sample's rock (the section under a scanline, a window's faces and edge) depends on the mesh, the photos
and the sample alone, so when the traces change the samples are measured again on the rock found before:
only the counting runs again. A subclass names its storage and says how to measure, report and draw.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from PySide6.QtCore import QObject, Signal
from PySide6.QtWidgets import QListWidget, QPushButton, QTextBrowser, QWidget

from engine.errors import Progress, TracemapError
from tracemap_gui.commands import EditItems, Storage
from tracemap_gui.error_dialog import describe, show_error
from tracemap_gui.mesh_tracer import survey
from tracemap_gui.workers import Task

if TYPE_CHECKING:
    from engine.mesh import Mesh
    from engine.sight import Sight
    from tracemap_gui.viewer3d import Viewer3D

LIST_MIN_PX = 48


class SampleTool(QObject):
    """Stored samples (`items`, each with an `id` and a `label`), their `measures` by id (each with a
    `rock`), and why the others cannot be measured (`problems`, a mesh since replaced)."""

    measured = Signal()  # the stored samples were measured again and are shown
    noun = "sample"  # how task titles name one: "scanline", "scan circle"
    storage: Storage

    def __init__(self, viewer: Viewer3D):
        super().__init__(viewer)
        self.viewer, self.session = viewer, viewer.session
        self.items: list = []
        self.measures: dict[int, object] = {}
        self.problems: dict[int, str] = {}
        self._rocks: tuple[object, dict[int, object]] = (None, {})  # the mesh, and each sample's rock
        self._measuring: Task | None = None  # the latest measuring of the stored samples

    # -- what a tool says ------------------------------------------------------------------------------------

    def stored(self) -> list:
        """The samples the project holds."""
        raise NotImplementedError

    def measurer(self) -> Callable:
        """f(mesh, traces, item, sight, rock) -> measure, with what else it needs (the sets) bound now."""
        raise NotImplementedError

    def report(self, measure) -> dict:
        """A measure's readout in the readouts' frame."""
        raise NotImplementedError

    def summary_line(self, report: dict) -> str:
        raise NotImplementedError

    def readout(self, report: dict) -> str:
        """The selected sample's readout, and the pooled one of all."""
        raise NotImplementedError

    def draw(self) -> None:
        raise NotImplementedError

    def load_settings(self) -> None:
        """Show the project's settings of the tool's boxes (they are kept with the project)."""

    # -- the dock's list -------------------------------------------------------------------------------------

    def build_list(self, panel: QWidget) -> None:
        """The list of stored samples, the selected one's readout and its Remove button."""
        prefix = self.noun.replace(" ", "-")
        self.list = QListWidget(panel)
        self.list.setObjectName(f"{prefix}-list")
        self.list.currentRowChanged.connect(self._show_details)
        self.details = QTextBrowser(panel)
        self.details.setObjectName(f"{prefix}-details")
        for box in (self.list, self.details):  # they grow with the dock; a small least height keeps the window's
            box.setMinimumHeight(LIST_MIN_PX)
        self.remove_button = QPushButton("Remove", panel)
        self.remove_button.setObjectName(f"{prefix}-remove")
        self.remove_button.clicked.connect(self.remove_selected)

    def watch(self) -> None:
        """Follow the session: measure again on opening, on a change of the traces or the mesh."""
        self.session.opened.connect(self.reload)
        self.session.traces3d_changed.connect(self.reload)
        self.session.registration_changed.connect(self._show_list)
        self.session.closed.connect(self._closed)
        self.viewer.mesh_loaded.connect(lambda _: self.reload())
        self.reload()

    def _closed(self) -> None:
        self.action.setChecked(False)
        self.reload()

    def reload(self) -> None:
        """Measure the stored samples on the traces as they are (on a worker), then list and draw them."""
        if self._measuring is not None:
            self._measuring.cancel()
            self._measuring = None
        self.load_settings()
        self.items = self.stored() if self.session.is_open else []
        if not self.items or self.viewer.mesh is None:
            self._show({}, {})
            return
        mesh, rocks = self._rocks
        known = dict(rocks) if mesh is self.viewer.mesh else {}
        self._measuring = task = Task(f"Measuring {self.noun}s", _measure_all, self.viewer.mesh, self.survey_of(),
                                      self.session.traces3d(), self.items, known, self.measurer())
        task.signals.done.connect(self._measured)
        task.signals.failed.connect(lambda exc: show_error(self.viewer, f"Measuring {self.noun}s", exc))
        self.session.jobs.start(task)

    def _measured(self, result: tuple[dict, dict]) -> None:
        if self._measuring is None or self.sender() is not self._measuring.signals:
            return  # superseded by a newer measuring
        self._measuring = None
        self._show(*result)

    def _show(self, measures: dict[int, object], problems: dict[int, str]) -> None:
        self.measures, self.problems = measures, problems
        self._rocks = (self.viewer.mesh, {k: m.rock for k, m in measures.items()})
        self._show_list()
        self.draw()
        self.measured.emit()

    def reports(self) -> dict[int, dict]:
        """The measured samples' readouts by id, in the readouts' frame."""
        return {k: self.report(m) for k, m in self.measures.items()} if self.session.is_open else {}

    def _show_list(self) -> None:
        row = self.list.currentRow()
        self.list.blockSignals(True)
        self.list.clear()
        reports = self.reports()
        self.list.addItems([self.summary_line(reports[item.id]) if item.id in reports
                            else f"{item.label}: {self.problems.get(item.id, 'measuring…')}" for item in self.items])
        self.list.blockSignals(False)
        self.list.setCurrentRow(min(max(row, 0), self.list.count() - 1))
        self._show_details(self.list.currentRow())

    def _show_details(self, row: int) -> None:
        item = self.items[row] if 0 <= row < len(self.items) else None
        if item is None:
            self.details.setPlainText("")
        elif item.id in self.measures:
            self.details.setPlainText(self.readout(self.reports()[item.id]))
        else:
            self.details.setPlainText(f"{item.label}: {self.problems.get(item.id, 'measuring…')}")

    def selected(self):
        """The sample selected in the list, or None."""
        row = self.list.currentRow()
        return self.items[row] if 0 <= row < len(self.items) else None

    def remove_selected(self) -> None:
        item = self.selected()
        if item is not None:
            self.viewer.push(EditItems(self.session, self.storage, [item], [], f"Remove {item.label}", self.reload))

    def store(self, items: list, text: str) -> list | None:
        """Store new samples as one edit; them with their ids, or None when the edit failed (it was shown)."""
        command = EditItems(self.session, self.storage, [], items, text, self.reload)
        self.viewer.push(command)
        return None if any(item.id < 0 for item in command.added) else command.added

    def survey_of(self) -> Callable[[Progress], Sight]:
        """What a worker calls for the survey of the viewer's mesh: the session's ray tracer of it (built on
        the first call, shared with the other tools) and the photos' cameras."""
        mesh, cameras, tracers = self.viewer.mesh, self.session.cameras(), self.session.mesh_tracer
        return lambda progress: survey(mesh, cameras, None, tracers, progress)


def _measure_all(mesh: Mesh, sight: Callable[[Progress], Sight], traces: list, items: list, rocks: dict[int, object],
                 measure: Callable, *, progress: Progress) -> tuple[dict[int, object], dict[int, str]]:
    """Each sample's measure by id (with its rock from `rocks` where known; the survey is built only for
    the others), and why the others cannot be measured."""
    survey = sight(progress) if any(item.id not in rocks for item in items) else None
    measures, problems = {}, {}
    for k, item in enumerate(items):
        progress(k / len(items), f"measuring {item.label}")
        try:
            measures[item.id] = measure(mesh, traces, item, survey, rocks.get(item.id))
        except TracemapError as exc:  # a stored sample off a mesh since replaced: listed with the reason
            problems[item.id] = describe(exc)
    return measures, problems
