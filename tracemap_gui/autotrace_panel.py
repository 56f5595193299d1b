"""The auto-trace dock: every delineation parameter, a preview of each stage, and accept/reject of proposals.

The parameter editors are generated from `DelineationParams` (its fields, documented ranges and units), so
a parameter added to the engine appears here without a change. "Preview" runs on the part of the photo in
view (at most PREVIEW_SIDE pixels square), quickly, and again by itself after every change when "Live" is
on; "Run on photo" runs on the whole photo. Either way the proposals are drawn dashed over the photo; click
one with the Select tool to reject it, then Accept stores the others as one undoable edit.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PySide6.QtCore import QTimer, Signal
from PySide6.QtWidgets import (QCheckBox, QComboBox, QDockWidget, QDoubleSpinBox, QFileDialog, QFormLayout,
                               QHBoxLayout, QLabel, QPushButton, QScrollArea, QSpinBox, QVBoxLayout, QWidget)

from engine.delineate.params import SECTIONS, SETTING, DelineationParams, Range, read_params, write_params
from engine.errors import TracemapError
from engine.traces import network
from tracemap_gui import commands, delineation
from tracemap_gui.error_dialog import show_error
from tracemap_gui.photo_view import PhotoView
from tracemap_gui.session import Session
from tracemap_gui.trace_layer import ProposalLayer, StageOverlay
from tracemap_gui.workers import Task

PREVIEW_SIDE = 1024  # pixels: the largest preview region, so a live preview takes about a second
PREVIEW_MIN = 128  # pixels: the smallest, however far the view is zoomed in
LIVE_DELAY_MS = 400  # wait this long after the last change before a live preview
PHOTO = "photo only"
PARAMETER_FILES = "auto-trace parameters (*.json);;all files (*)"
SHORT_UNIT = 7  # characters: units this short are shown in the parameter's label


class ParameterForm(QWidget):
    """One editor per `DelineationParams` field: check box, choice list or spin box within its range."""

    changed = Signal()

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        layout = QFormLayout(self)
        self._editors: dict[str, QWidget] = {}
        for f in dataclasses.fields(DelineationParams):
            if f.name in SECTIONS:
                heading = QLabel(f"<b>{SECTIONS[f.name].capitalize()}</b>")
                heading.setObjectName(f"section-{f.name}")
                layout.addRow(heading)
            editor = self._editor(f.default, f.metadata["range"])
            unit = f.metadata["unit"]
            editor.setToolTip(f"{f.metadata['doc']}\n{f.metadata['range']}" + (f", {unit}" if unit else ""))
            editor.setObjectName(f"param-{f.name}")
            short = unit and len(unit) <= SHORT_UNIT  # a long unit ("grey levels (0–255)") stays in the tip
            layout.addRow(f.name + (f" ({unit})" if short else ""), editor)
            self._editors[f.name] = editor
        self.set_values(dataclasses.asdict(DelineationParams()))

    def _editor(self, default: object, allowed: Range) -> QWidget:
        if isinstance(default, bool):
            editor = QCheckBox()
            editor.toggled.connect(self.changed)
        elif allowed.choices:
            editor = QComboBox()
            editor.addItems([str(c) for c in allowed.choices])
            editor.currentIndexChanged.connect(self.changed)
        elif isinstance(default, int):
            editor = QSpinBox()
            editor.setRange(int(max(allowed.lo, -2**31)), int(min(allowed.hi, 2**31 - 1)))
            editor.setSingleStep(2 if allowed.odd else 1)
            editor.valueChanged.connect(self.changed)
        else:
            editor = QDoubleSpinBox()
            editor.setDecimals(3)
            nudge = 10 ** -editor.decimals()  # an open end is not allowed itself
            lo = -1e9 if math.isinf(allowed.lo) else allowed.lo + (nudge if allowed.lo_open else 0)
            hi = 1e9 if math.isinf(allowed.hi) else allowed.hi - (nudge if allowed.hi_open else 0)
            editor.setRange(lo, hi)
            # arrows step by a tenth of the default's leading digit: 2.1 by 0.1, 0.55 by 0.01, 50 by 1
            editor.setSingleStep(10.0 ** (math.floor(math.log10(abs(default))) - 1) if default else 0.01)
            editor.valueChanged.connect(self.changed)
        return editor

    def values(self) -> dict[str, object]:
        out: dict[str, object] = {}
        for f in dataclasses.fields(DelineationParams):
            editor = self._editors[f.name]
            if isinstance(editor, QCheckBox):
                out[f.name] = editor.isChecked()
            elif isinstance(editor, QComboBox):
                out[f.name] = f.metadata["range"].choices[editor.currentIndex()]
            else:
                out[f.name] = editor.value()
        return out

    def params(self) -> DelineationParams:
        """The parameters shown; an `InputError` names a value out of range."""
        return DelineationParams(**self.values())

    def set_values(self, values: dict[str, object]) -> None:
        for f in dataclasses.fields(DelineationParams):
            if f.name not in values:
                continue
            editor, value = self._editors[f.name], values[f.name]
            editor.blockSignals(True)
            if isinstance(editor, QCheckBox):
                editor.setChecked(bool(value))
            elif isinstance(editor, QComboBox):
                choices = f.metadata["range"].choices
                editor.setCurrentIndex(choices.index(value) if value in choices else 0)
            else:
                editor.setValue(value)
            editor.blockSignals(False)
        self.changed.emit()


class AutotracePanel(QDockWidget):
    """Run auto-trace on the shown photo, preview its stages, and accept or reject its proposals."""

    def __init__(self, session: Session, view: PhotoView, proposals: ProposalLayer, overlay: StageOverlay,
                 parent: QWidget | None = None):
        super().__init__("Auto-trace", parent)
        self.setObjectName("autotrace-dock")
        self._session, self._view, self._proposals, self._overlay = session, view, proposals, overlay
        self._no_mesh = ""  # why the last run went without the mesh's silhouette
        self._task: Task | None = None
        self.result: delineation.AutotraceRun | None = None
        self.form = ParameterForm()
        self._build()
        self._live_timer = QTimer(self, singleShot=True, interval=LIVE_DELAY_MS)
        self._live_timer.timeout.connect(lambda: self.run(whole=False, live=True))
        self.form.changed.connect(self._schedule_live)
        view.view_changed.connect(self._schedule_live)
        proposals.changed.connect(self._show_counts)
        session.opened.connect(self._load_parameters)
        if session.is_open:
            self._load_parameters()

    def _build(self) -> None:
        scroll = QScrollArea()
        scroll.setWidget(self.form)
        scroll.setWidgetResizable(True)
        self.stage = QComboBox()
        self.stage.addItems([PHOTO, *delineation.STAGES])
        self.stage.setToolTip("the intermediate of the last run to draw over the photo")
        self.stage.currentTextChanged.connect(self._show_stage)
        self.live = QCheckBox("Live")
        self.live.setToolTip("preview the part in view again after every change")
        self.live.toggled.connect(self._schedule_live)
        self.preview_button = QPushButton("Preview view")
        self.run_button = QPushButton("Run on photo")
        self.accept_button = QPushButton("Accept")
        self.reject_button = QPushButton("Reject")
        defaults = QPushButton("Defaults")
        self.load_button = QPushButton("Load…")
        self.load_button.setToolTip("parameters from a JSON file (as Save writes, or `tracemap autotrace --params`)")
        self.save_button = QPushButton("Save…")
        self.save_button.setToolTip("the parameters shown, to a JSON file for other projects or the command line")
        self.load_button.clicked.connect(self.load_parameters)
        self.save_button.clicked.connect(self.save_parameters)
        self.preview_button.clicked.connect(lambda: self.run(whole=False))
        self.run_button.clicked.connect(lambda: self.run(whole=True))
        self.accept_button.clicked.connect(self.accept)
        self.reject_button.clicked.connect(self.reject)
        defaults.clicked.connect(lambda: self.form.set_values(dataclasses.asdict(DelineationParams())))
        self.status = QLabel()
        self.status.setWordWrap(True)
        body = QWidget()
        layout = QVBoxLayout(body)
        layout.addWidget(scroll, 1)
        for row in ((QLabel("Show"), self.stage, self.live), (self.preview_button, self.run_button),
                    (defaults, self.load_button, self.save_button), (self.accept_button, self.reject_button)):
            line = QHBoxLayout()
            for widget in row:
                line.addWidget(widget)
            layout.addLayout(line)
        layout.addWidget(self.status)
        self.setWidget(body)
        self._show_counts()

    # -- running --------------------------------------------------------------------------------------

    def run(self, whole: bool, live: bool = False) -> None:
        """Auto-trace the photo (whole) or the part in view, on a worker; a run still going is cancelled.

        live : started by a change with Live on: a bad parameter is told in the panel, not in a dialog.
        """
        if self._view.pyramid is None:
            self.status.setText("the photo is still loading")
            return
        try:
            params = self.form.params()
        except TracemapError as exc:
            if live:
                self.status.setText(str(exc))
            else:
                show_error(self, "Auto-trace", exc)
            return
        self._session.set_setting(SETTING, dataclasses.asdict(params))
        pixels, origin = self._region(whole)
        if self._task is not None:
            self._task.cancel()
        image = self._view.image
        task = Task(f"Auto-trace {image}" + ("" if whole else " (view)"), delineation.run_autotrace,
                    image, pixels, params, origin, self._silhouette_of(image, params), self._support_of(image, params),
                    self._kinds_of(image, params))
        task.signals.done.connect(lambda run: self._finished(task, run))
        task.signals.failed.connect(lambda exc: show_error(self, "Auto-trace", exc))
        task.signals.ended.connect(lambda: self._ended(task))
        self._task = self._session.jobs.start(task)
        self.status.setText("running…")

    def _silhouette_of(self, image: str, params: DelineationParams) -> Callable[..., np.ndarray] | None:
        """What gives the mesh's silhouette in the photo on the worker, or None: turned off, or no usable mesh
        (the run goes on without it and the panel says why)."""
        self._no_mesh = ""
        if not params.silhouette:
            return None
        try:
            mesh_path = self._session.project.mesh_path
        except TracemapError as exc:
            self._no_mesh = f"without the mesh's silhouette: {exc}"
            return None
        return functools.partial(self._session.mesh_tracer.silhouette, self._session.camera(image),
                                 params.silhouette_step, mesh_path, self._session.project.origin)

    def _support_of(self, image: str, params: DelineationParams) -> Callable[..., list[np.ndarray]] | None:
        """What gives, on the worker, the segments the run turned down that the other photos' traces (as they
        are now in the project) support; None when turned off or without a usable mesh."""
        if not params.support:
            return None
        try:
            mesh_path = self._session.project.mesh_path
        except TracemapError as exc:
            self._no_mesh = self._no_mesh or f"without support from the other photos: {exc}"
            return None
        kept = {name: [t.polyline for t in network(self._session.traces2d(name)) if name != image or t.source == "manual"]
                for name in self._session.images()}  # the run replaces the photo's auto traces; bedding supports none
        tracer_of = functools.partial(self._session.mesh_tracer.tracer, mesh_path, self._session.project.origin)
        return functools.partial(delineation.support_in_photo, image, kept, self._session.cameras(), params,
                                 tracer_of)

    def _kinds_of(self, image: str, params: DelineationParams) -> Callable[..., list] | None:
        """What gives, on the worker, the run's proposals the kinds the other photos' traces of them have (as
        they are now in the project); None when support is off or without a usable mesh."""
        if not params.support:
            return None
        try:
            mesh_path = self._session.project.mesh_path
        except TracemapError:
            return None  # `_support_of` says so
        others = [t for name in self._session.images() if name != image for t in self._session.traces2d(name)]
        tracer_of = functools.partial(self._session.mesh_tracer.tracer, mesh_path, self._session.project.origin)
        return functools.partial(delineation.kinds_in_photo, image, others, self._session.cameras(), params,
                                 tracer_of)

    def _region(self, whole: bool) -> tuple[np.ndarray, tuple[int, int]]:
        """The photo, or the part in view: at most PREVIEW_SIDE and at least PREVIEW_MIN pixels square."""
        pixels = self._view.pyramid.levels[0]
        if whole:
            return pixels, (0, 0)
        h, w = pixels.shape[:2]
        shown = self._view.mapToScene(self._view.viewport().rect()).boundingRect()
        side_x = int(min(max(shown.width(), PREVIEW_MIN), PREVIEW_SIDE, w))
        side_y = int(min(max(shown.height(), PREVIEW_MIN), PREVIEW_SIDE, h))
        x0 = int(np.clip(round(shown.center().x() - side_x / 2), 0, w - side_x))
        y0 = int(np.clip(round(shown.center().y() - side_y / 2), 0, h - side_y))
        return pixels[y0:y0 + side_y, x0:x0 + side_x], (x0, y0)

    def _finished(self, task: Task, run: delineation.AutotraceRun) -> None:
        if task is not self._task or run.image != self._view.image:
            return  # superseded, or the user moved to another photo
        self.result = run
        self._no_mesh = self._no_mesh or run.note
        self._proposals.set(run.image, run.proposals)
        self._show_stage(self.stage.currentText())

    def _ended(self, task: Task) -> None:
        if task is self._task:
            self._task = None
            self._show_counts()

    # -- proposals ------------------------------------------------------------------------------------

    def accept(self) -> None:
        image = self._proposals.image
        if image is None:
            return
        self._session.push(commands.ReplaceAutoTraces(self._session, image, self._proposals.accepted()))
        self._proposals.clear()

    def reject(self) -> None:
        self._proposals.clear()

    def photo_changed(self) -> None:
        """Another photo is shown: the last run belonged to the previous one."""
        if self._task is not None:
            self._task.cancel()
        self.result = None
        self._proposals.clear()
        self._overlay.clear()

    # -- display --------------------------------------------------------------------------------------

    def _show_stage(self, name: str) -> None:
        stage = None if self.result is None else self.result.stages.get(name)
        if stage is None:
            self._overlay.clear()
        elif stage.image is not None:
            self._overlay.show_image(stage.image, self.result.origin)
        else:
            self._overlay.show_polylines(stage.polylines)
        self._show_counts()

    def _show_counts(self) -> None:
        n, rejected = len(self._proposals.traces), len(self._proposals.rejected)
        lines = []
        if self._task is not None:
            lines.append("running…")
        if self.result is not None:
            supported = f" ({self.result.supported} from the other photos)" if self.result.supported else ""
            lines.append(f"{n} proposals{supported}, {rejected} rejected")
        if self._no_mesh:
            lines.append(self._no_mesh)
        self.status.setText("\n".join(lines))
        self.accept_button.setEnabled(n > rejected)
        self.reject_button.setEnabled(n > 0)

    def _schedule_live(self) -> None:
        if self.live.isChecked():
            self._live_timer.start()
        else:
            self._live_timer.stop()

    def load_parameters(self) -> None:
        """Show the parameters of a file the user picks; a bad file is a message, and the form is unchanged."""
        path, _ = QFileDialog.getOpenFileName(self, "Load auto-trace parameters", "", PARAMETER_FILES)
        if not path:
            return
        try:
            params = read_params(path)
        except TracemapError as exc:
            show_error(self, "Loading auto-trace parameters", exc)
            return
        self.form.set_values(dataclasses.asdict(params))
        self.status.setText(f"parameters from {Path(path).name}")

    def save_parameters(self) -> None:
        """Write the parameters shown to a file the user picks (refused while one is out of range)."""
        try:
            params = self.form.params()
        except TracemapError as exc:
            show_error(self, "Saving auto-trace parameters", exc)
            return
        path, _ = QFileDialog.getSaveFileName(self, "Save auto-trace parameters", "autotrace.json",
                                              PARAMETER_FILES)
        if not path:
            return
        try:
            write_params(params, path)
        except OSError as exc:
            show_error(self, "Saving auto-trace parameters", exc)
            return
        self.status.setText(f"parameters saved to {Path(path).name}")

    def _load_parameters(self) -> None:
        defaults = dataclasses.asdict(DelineationParams())
        values = {**defaults, **self._session.setting(SETTING, {})}
        try:
            DelineationParams(**values)
        except (TracemapError, TypeError):
            values = defaults  # stored by another version of tracemap: start from the defaults
        self.form.set_values(values)
