"""The plots dock of the 3D viewer: stereonet, lengths, Kaplan–Meier, terminations and summary, one tab each.

The plots are `engine.plots` figures, so the window shows what `tracemap plot` writes. They follow the
session: a short while after the traces change or a project opens, the plot data is read (GUI thread: the
project belongs to it) and the figures are built on a worker, a build still running being cancelled.
Each tab exports its figure (PNG or SVG) and its data (CSV). While the dock is hidden nothing is built;
it catches up when shown.
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg
from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtWidgets import (QDockWidget, QFileDialog, QHBoxLayout, QLabel, QMainWindow, QPushButton,
                               QTabWidget, QVBoxLayout, QWidget)

from engine.plots import Plot, build_plots, plot_data, save_figure, write_table_csv
from tracemap_gui.error_dialog import show_error
from tracemap_gui.session import Session
from tracemap_gui.workers import Task

REFRESH_DELAY_MS = 300  # after the last change: a burst of edits (drag, undo run) rebuilds the plots once
MIN_CANVAS = (360, 280)  # pixels: smaller, the figures' constrained layout collapses
IMAGE_FILTERS = {"PNG image (*.png)": ".png", "SVG image (*.svg)": ".svg"}


class PlotsPanel(QDockWidget):
    """A tab per plot of the session's project, rebuilt after every change of its traces."""

    refreshed = Signal()  # new plots are shown

    def __init__(self, session: Session, parent: QWidget | None = None):
        super().__init__("Plots", parent)
        self.setObjectName("plots-dock")
        self.session = session
        self.plots: dict[str, Plot] = {}
        self.tabs = QTabWidget(self)
        self.tabs.setObjectName("plots-tabs")
        self.setWidget(self.tabs)
        self._task: Task | None = None
        self._stale = False
        self._timer = QTimer(self, singleShot=True, interval=REFRESH_DELAY_MS)
        self._timer.timeout.connect(self.refresh)
        session.opened.connect(self.schedule)
        session.traces3d_changed.connect(self.schedule)
        session.closed.connect(self._clear)
        self.visibilityChanged.connect(lambda visible: visible and self._stale and self.schedule())
        if session.is_open:
            self.schedule()

    # -- building -------------------------------------------------------------------------------------

    def schedule(self) -> None:
        """Rebuild the plots soon (debounced), or once the dock is shown."""
        self._stale = not self.isVisible()
        if not self._stale:
            self._timer.start()

    def refresh(self) -> None:
        """Read the plot data now and build the figures on a worker."""
        if not self.session.is_open:
            return
        try:
            data = plot_data(self.session.project, self.session.traces3d())
        except Exception as exc:  # noqa: BLE001 - shown to the user; the old plots stay
            show_error(self, "Reading the plot data", exc)
            return
        if self._task is not None:
            self._task.cancel()
        task = Task("Updating plots", build_plots, data)
        task.signals.done.connect(self._show)
        task.signals.failed.connect(lambda exc: show_error(self, "Updating the plots", exc))
        task.signals.ended.connect(lambda: self._ended(task))
        self._task = self.session.jobs.start(task)

    def _ended(self, task: Task) -> None:
        if self._task is task:
            self._task = None

    def _show(self, plots: dict[str, Plot]) -> None:
        current = self.tabs.tabText(self.tabs.currentIndex())
        self._clear()
        self.plots = plots
        for plot in plots.values():
            self.tabs.addTab(self._page(plot), plot.title)
            if plot.title == current:
                self.tabs.setCurrentIndex(self.tabs.count() - 1)
        self.refreshed.emit()

    def _page(self, plot: Plot) -> QWidget:
        page = QWidget()
        page.setObjectName(f"plot-{plot.name}")
        layout = QVBoxLayout(page)
        if plot.figure is None:
            reason = QLabel(f"Not available: {plot.reason}")
            reason.setObjectName("plot-reason")
            reason.setWordWrap(True)
            reason.setAlignment(Qt.AlignmentFlag.AlignCenter)
            layout.addWidget(reason)
            return page
        canvas = FigureCanvasQTAgg(plot.figure)
        canvas.setMinimumSize(*MIN_CANVAS)
        layout.addWidget(canvas, 1)
        buttons = QHBoxLayout()
        for text, name, slot in (("Export PNG/SVG…", "export-image", self._ask_image),
                                 ("Export data CSV…", "export-table", self._ask_table)):
            button = QPushButton(text)
            button.setObjectName(name)
            button.clicked.connect(lambda _=False, p=plot.name, f=slot: f(p))
            buttons.addWidget(button)
        buttons.addStretch(1)
        layout.addLayout(buttons)
        return page

    def _clear(self) -> None:
        while self.tabs.count():
            page = self.tabs.widget(0)
            self.tabs.removeTab(0)
            page.deleteLater()
        self.plots = {}

    # -- exporting ------------------------------------------------------------------------------------

    def export_image(self, name: str, path: str | Path) -> None:
        """Save the figure of plot `name` as PNG or SVG (by the suffix of `path`)."""
        self._export(f"Exporting the {name} plot", lambda: save_figure(self.plots[name].figure, path), path)

    def export_table(self, name: str, path: str | Path) -> None:
        """Save the data of plot `name` as CSV."""
        self._export(f"Exporting the {name} data", lambda: write_table_csv(self.plots[name].table, path), path)

    def _export(self, doing: str, write, path: str | Path) -> None:
        try:
            write()
        except Exception as exc:  # noqa: BLE001 - shown to the user
            show_error(self, doing, exc)
            return
        if isinstance(window := self.parent(), QMainWindow):
            window.statusBar().showMessage(f"saved {path}", 5000)

    def _ask_image(self, name: str) -> None:
        path, chosen = QFileDialog.getSaveFileName(self, "Export plot", f"{name}.png", ";;".join(IMAGE_FILTERS))
        if path:
            self.export_image(name, path if Path(path).suffix else path + IMAGE_FILTERS.get(chosen, ".png"))

    def _ask_table(self, name: str) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Export plot data", f"{name}.csv", "CSV table (*.csv)")
        if path:
            self.export_table(name, path if Path(path).suffix else path + ".csv")
