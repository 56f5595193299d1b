"""The 3D viewer's Analysis menu: the desktop's `tracemap orient` and `tracemap analyse` (without intensity maps,
which the maps panel computes).

"Orient traces…" and "Analyse terminations and lengths…" each ask for the command line's options in a small
dialog, then run the engine (`engine.analysis.orient_and_classify`, `measure_traces`) on a worker with a
snapshot of the traces, progress and Cancel in the status bar. What a run finds is stored as one undoable
edit (`commands.StoreAnalysis3D`): the traces' poles and sets, or their termination codes and groups, with the
results the plots show. A run whose traces were edited meanwhile stores nothing: it would undo that edit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from PySide6.QtCore import QObject, Qt
from PySide6.QtGui import QAction
from PySide6.QtWidgets import QDoubleSpinBox, QSpinBox, QToolBar, QWidget

from engine.analysis import K_THRESHOLD, N_BOOTSTRAP, describe_topology, measure_traces, orient_and_classify
from engine.cameras import Camera
from engine.errors import Progress
from engine.mesh import Mesh
from engine.sets import Facet
from engine.topology import TOLERANCE_SCALE
from engine.traces import Trace3D
from tracemap_gui.commands import StoreAnalysis3D
from tracemap_gui.error_dialog import show_error
from tracemap_gui.value_dialog import ValueDialog
from tracemap_gui.workers import Task

if TYPE_CHECKING:
    from tracemap_gui.viewer3d import Viewer3D

MAX_SETS = 99  # the spin box's top; the engine says when the traces cannot make that many
Outcome = tuple[list[Trace3D], dict[str, object], str]  # a run's traces, its results and a line for the status bar


class OrientDialog(ValueDialog):
    """`tracemap orient`'s options: the number of sets (automatic or N) and the K threshold."""

    def __init__(self, parent: QWidget | None = None):
        super().__init__("Orient traces", "orient-dialog", parent)
        self.sets = QSpinBox(self)
        self.sets.setObjectName("orient-sets")
        self.sets.setRange(0, MAX_SETS)
        self.sets.setSpecialValueText("automatic (BIC)")  # shown for 0
        self.sets.setToolTip("how many fracture sets to fit; automatic chooses the number by BIC")
        self.k_threshold = QDoubleSpinBox(self)
        self.k_threshold.setObjectName("orient-k-threshold")
        self.k_threshold.setRange(0.01, 100.0)
        self.k_threshold.setSingleStep(0.1)
        self.k_threshold.setValue(K_THRESHOLD)
        self.k_threshold.setToolTip("collinearity K above which a trace is oriented by the probabilistic solver")
        self.add_row("Number of sets", self.sets)
        self.add_row("K threshold", self.k_threshold)

    def parse(self) -> dict[str, object]:
        return {"n_sets": self.sets.value() or None, "k_threshold": self.k_threshold.value()}


class AnalyseDialog(ValueDialog):
    """`tracemap analyse`'s options: the topology tolerance and the bootstrap samples."""

    def __init__(self, parent: QWidget | None = None):
        super().__init__("Analyse terminations and lengths", "analyse-dialog", parent)
        self.scale = QDoubleSpinBox(self)
        self.scale.setObjectName("analyse-scale")
        self.scale.setRange(0.1, 100.0)
        self.scale.setSingleStep(0.5)
        self.scale.setSuffix(" × GSD")
        self.scale.setValue(TOLERANCE_SCALE)
        self.scale.setToolTip("how near (in ground sampling distances, the size of a pixel on the outcrop) an end "
                              "must come to another trace to abut or cross it")
        self.bootstrap = QSpinBox(self)
        self.bootstrap.setObjectName("analyse-bootstrap")
        self.bootstrap.setRange(0, 100_000)
        self.bootstrap.setValue(N_BOOTSTRAP)
        self.bootstrap.setToolTip("samples of the parametric bootstrap of the length fits' p-values (0: none)")
        self.add_row("Topology tolerance", self.scale)
        self.add_row("Bootstrap samples", self.bootstrap)

    def parse(self) -> dict[str, object]:
        return {"scale": self.scale.value(), "n_bootstrap": self.bootstrap.value()}


class AnalysisMenu(QObject):
    """The Analysis menu (and toolbar buttons) of the 3D viewer, and the one run it may have going."""

    def __init__(self, viewer: Viewer3D):
        super().__init__(viewer)
        self.viewer = viewer
        self.session = viewer.session
        self.orient_action = self._action("Orient traces…", "orient-traces", self.ask_orient,
                                          "Orient the 3D traces (eigen + probabilistic solver) and fit their sets")
        self.analyse_action = self._action("Analyse terminations and lengths…", "analyse-traces", self.ask_analyse,
                                           "Classify the trace ends, find the connected groups, measure the lengths")
        self.menu = viewer.menuBar().addMenu("&Analysis")
        self.menu.addActions([self.orient_action, self.analyse_action])
        viewer.findChild(QToolBar, "viewer3d-toolbar").addActions([self.orient_action, self.analyse_action])
        self.task: Task | None = None

    def _action(self, text: str, name: str, slot: Callable[[], None], tip: str) -> QAction:
        action = QAction(text, self.viewer)
        action.setObjectName(name)
        action.setStatusTip(tip)
        action.triggered.connect(slot)
        return action

    # -- asking ---------------------------------------------------------------------------------------

    def ask_orient(self) -> None:
        self._ask(OrientDialog, "Orienting the traces", self.orient)

    def ask_analyse(self) -> None:
        self._ask(AnalyseDialog, "Analysing the traces", self.analyse)

    def _ask(self, make: Callable[[QWidget], ValueDialog], doing: str, run: Callable[..., Task | None]) -> None:
        """Open the options dialog (non-blocking) unless the run could not start now; OK starts it."""
        if self._refused(doing) is None:
            return
        dialog = make(self.viewer)
        dialog.setAttribute(Qt.WidgetAttribute.WA_DeleteOnClose)
        dialog.accepted.connect(lambda: run(**dialog.values))
        dialog.open()

    # -- running --------------------------------------------------------------------------------------

    def orient(self, *, n_sets: int | None = None, k_threshold: float = K_THRESHOLD) -> Task | None:
        """Orient the traces and fit their sets on a worker; the started task, or None (a dialog says why)."""
        traces = self._refused("Orienting the traces")
        if traces is None:
            return None
        return self._start("Orienting the traces", "Orient traces", traces, _orient, self.viewer.mesh,
                           self.session.project.facets(), n_sets=n_sets, k_threshold=k_threshold)

    def analyse(self, *, scale: float = TOLERANCE_SCALE, n_bootstrap: int = N_BOOTSTRAP) -> Task | None:
        """Terminations, connected groups and lengths on a worker; the started task, or None (a dialog says why)."""
        traces = self._refused("Analysing the traces")
        if traces is None:
            return None
        return self._start("Analysing the traces", "Analyse terminations and lengths", traces, _analyse,
                           self.viewer.mesh, self.session.cameras(), scale=scale, n_bootstrap=n_bootstrap)

    def _refused(self, doing: str) -> list[Trace3D] | None:
        """The traces to run on, or None after a dialog saying why the run cannot start now."""
        problem = ("no project is open" if not self.session.is_open
                   else "another analysis is running; wait for it or cancel it" if self.task is not None
                   else "the mesh is still loading; try again once it is shown" if self.viewer.mesh is None
                   else "there are no 3D traces; extract them from the photos first (image editor)"
                   if not self.session.traces3d() else None)
        if problem is not None:
            show_error(self.viewer, doing, problem)
            return None
        return list(self.session.traces3d())

    def _start(self, doing: str, text: str, traces: list[Trace3D], work: Callable[..., Outcome],
               *args: object, **kwargs: object) -> Task:
        task = self.task = Task(text, work, traces, *args, **kwargs)
        task.signals.done.connect(lambda outcome: self._store(doing, text, traces, outcome))
        task.signals.failed.connect(lambda exc: show_error(self.viewer, doing, exc))
        task.signals.cancelled.connect(
            lambda: self.viewer.statusBar().showMessage(f"{text}: cancelled; nothing was changed", 5000))
        task.signals.ended.connect(self._ended)
        self._enable(False)
        return self.session.jobs.start(task)

    def _store(self, doing: str, text: str, snapshot: list[Trace3D], outcome: Outcome) -> None:
        traces, results, summary = outcome
        if not self._unchanged(snapshot):
            show_error(self.viewer, doing, "the 3D traces were edited while it ran, so nothing was stored (it "
                                           "would have undone the edit); run it again")
            return
        try:
            self.session.push_in_background(StoreAnalysis3D(self.session, traces, results, text))
        except Exception as exc:  # noqa: BLE001 - shown to the user; nothing was stored
            show_error(self.viewer, doing, exc)
            return
        self.viewer.statusBar().showMessage(summary, 15_000)

    def _unchanged(self, snapshot: list[Trace3D]) -> bool:
        """Whether the session's traces are still those of `snapshot`: every edit (and its undo) replaces the
        cached objects of the traces it touches."""
        now = self.session.traces3d() if self.session.is_open else []
        return len(now) == len(snapshot) and all(a is b for a, b in zip(now, snapshot))

    def _ended(self) -> None:
        self.task = None
        self._enable(True)

    def _enable(self, on: bool) -> None:
        for action in (self.orient_action, self.analyse_action):
            action.setEnabled(on)


def _orient(traces: list[Trace3D], mesh: Mesh, facets: list[Facet], *, n_sets: int | None, k_threshold: float,
            progress: Progress) -> Outcome:
    """On a worker: `tracemap orient`'s computation."""
    run = orient_and_classify(traces, mesh, facets=facets, n_sets=n_sets, k_threshold=k_threshold,
                              progress=progress)
    return run.traces, run.results, run.summary


def _analyse(traces: list[Trace3D], mesh: Mesh, cameras: dict[str, Camera], *, scale: float, n_bootstrap: int,
             progress: Progress) -> Outcome:
    """On a worker: `tracemap analyse`'s computation, without intensity maps."""
    run = measure_traces(traces, mesh, cameras, scale=scale, n_bootstrap=n_bootstrap, progress=progress)
    return run.traces, run.results, describe_topology(run.topology)
