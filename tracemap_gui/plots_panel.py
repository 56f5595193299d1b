"""The plots dock of the 3D viewer: stereonet, lengths, Kaplan–Meier, terminations and summary, one tab each.

The plots are `engine.plots` figures, so the window shows what `tracemap plot` writes. They follow the
session: a short while after the traces change or a project opens, a worker reads the plot data (through
a connection of its own, `Project.for_thread`: the maps' blobs took the GUI thread 20–70 ms) and builds the
figures, a build still running being cancelled. The worker also draws them (Agg, at the size of the tab):
drawing the five figures takes ~1 s, which on the GUI thread froze the window (issue 5); the tabs only show
the pictures. After the dock is resized, the figures are drawn again at the new size, on a worker too;
meanwhile the old pictures are scaled. Each tab exports its figure (PNG or SVG) and its data (CSV). While
the dock is hidden nothing is built; it catches up when shown.
"""

from __future__ import annotations

import gc
import threading
from pathlib import Path

import matplotlib as mpl
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PySide6.QtCore import QRectF, QSize, Qt, QTimer, Signal
from PySide6.QtGui import QColor, QImage, QPainter
from PySide6.QtWidgets import (QDockWidget, QFileDialog, QHBoxLayout, QLabel, QMainWindow, QPushButton,
                               QStackedWidget, QTabWidget, QVBoxLayout, QWidget)

from engine.errors import Progress, report
from engine.plots import Plot, build_plots, plot_data, save_figure, write_table_csv
from engine.project import Project
from engine.register import Similarity
from engine.scan_circle import WindowMeasure, scan_circle_plot
from engine.scanline import ScanlineMeasure, scanline_plot
from engine.traces import Trace3D
from tracemap_gui.error_dialog import show_error
from tracemap_gui.session import Session
from tracemap_gui.workers import Task

REFRESH_DELAY_MS = 300  # after the last change: a burst of edits (drag, undo run) rebuilds the plots once
MIN_CANVAS = (360, 280)  # pixels: smaller, the figures' constrained layout collapses
PAGE_MARGIN = 6  # pixels round a tab's picture and buttons, and between them
IMAGE_FILTERS = {"PNG image (*.png)": ".png", "SVG image (*.svg)": ".svg"}


class PlotsPanel(QDockWidget):
    """A tab per plot of the session's project, rebuilt after every change of its traces."""

    refreshed = Signal()  # new plots are shown

    def __init__(self, session: Session, parent: QWidget | None = None):
        super().__init__("Plots", parent)
        self.setObjectName("plots-dock")
        self.session = session
        self.plots: dict[str, Plot] = {}
        self.scanlines: list[ScanlineMeasure] = []  # the 3D viewer's measured scanlines: a tab each
        self.windows: list[WindowMeasure] = []  # its measured scan circles: one tab of them all
        self.tabs = QTabWidget()
        self.tabs.setObjectName("plots-tabs")
        # said above the plots while they show results computed before the traces last changed
        self.out_of_date = QLabel()
        self.out_of_date.setObjectName("plots-out-of-date")
        self.out_of_date.setWordWrap(True)
        self.out_of_date.setStyleSheet("color: #a15c00")
        self.out_of_date.hide()
        body = QWidget(self)
        column = QVBoxLayout(body)
        column.setContentsMargins(0, 0, 0, 0)
        column.addWidget(self.out_of_date)
        column.addWidget(self.tabs, 1)
        self.setWidget(body)
        self._task: Task | None = None
        self._stale = False
        self._drawn_at: tuple[int, int, float] | None = None  # (width, height, pixel ratio) of the pictures
        self._figures = threading.Lock()  # a figure is drawn by one thread at a time: a worker or an export
        self._timer = QTimer(self, singleShot=True, interval=REFRESH_DELAY_MS)
        self._timer.timeout.connect(self.refresh)
        self._resize_timer = QTimer(self, singleShot=True, interval=REFRESH_DELAY_MS)
        self._resize_timer.timeout.connect(self._redraw)
        session.opened.connect(self.schedule)
        session.traces3d_changed.connect(self.schedule)
        session.registration_changed.connect(self.schedule)
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
        """Read the plot data, build and draw the figures, on a worker (the old plots stay if it fails)."""
        if not self.session.is_open:
            return
        if self.session.reading_traces3d:  # not waited for here: after opening, try again a little later
            self._timer.start()
            return
        self._start(Task("Updating plots", _read_build_and_draw, self.session.project, self.session.traces3d(),
                         list(self.scanlines), list(self.windows), self.session.similarity(),
                         self._picture_size(), self._figures),
                    self._show)

    def set_scanlines(self, measures: list[ScanlineMeasure]) -> None:
        """Show a tab of cumulative crossings (`engine.scanline.scanline_plot`) for each of these scanlines."""
        self.scanlines = list(measures)
        self.schedule()

    def set_scan_circles(self, measures: list[WindowMeasure]) -> None:
        """Show a tab of these scan circles on the face (`engine.scan_circle.scan_circle_plot`), if any."""
        self.windows = list(measures)
        self.schedule()

    def _redraw(self) -> None:
        """Draw the shown figures again at the pictures' new size, on a worker."""
        size = self._picture_size()
        if self._task is None and self.plots and self.isVisible() and size != self._drawn_at:
            self._start(Task("Drawing plots", _draw_all, self.plots, size, self._figures), self._show_pictures)

    def _start(self, task: Task, done) -> None:
        if self._task is not None:
            self._task.cancel()
        task.signals.done.connect(done)
        task.signals.failed.connect(lambda exc: show_error(self, "Updating the plots", exc))
        task.signals.ended.connect(self._ended)  # a bound method: Qt drops it with the panel
        self._task = self.session.jobs.start(task)

    def _ended(self) -> None:
        if self._task is not None and self.sender() is self._task.signals:
            self._task = None
            if self.plots and self.isVisible() and self._picture_size() != self._drawn_at:  # resized meanwhile
                self._resize_timer.start()

    def _picture_size(self) -> tuple[int, int, float]:
        """Logical width and height of a tab's picture, and the screen's device pixel ratio."""
        page = self.tabs.currentWidget()
        picture = None if page is None else page.findChild(FigurePicture)
        if picture is not None:
            width, height = picture.width(), picture.height()
        else:  # none laid out yet: what a page (`_page`) leaves of the tabs' page area
            area = self.tabs.findChild(QStackedWidget).size()
            buttons = QPushButton("Export").sizeHint().height()
            width, height = area.width() - 2 * PAGE_MARGIN, area.height() - 3 * PAGE_MARGIN - buttons
        return max(width, MIN_CANVAS[0]), max(height, MIN_CANVAS[1]), self.devicePixelRatioF()

    def _show(self, built: tuple[dict[str, Plot], dict[str, np.ndarray], tuple[int, int, float], tuple[str, ...]]
              ) -> None:
        plots, pictures, size, stale = built
        current = self.tabs.tabText(self.tabs.currentIndex())
        self._clear()
        self.out_of_date.setText(f"The {', '.join(stale)} shown were computed before the 3D traces last changed; "
                                 f"update them with {_remedy(stale)}.")
        self.out_of_date.setVisible(bool(stale))
        self.plots = plots
        for plot in plots.values():
            self.tabs.addTab(self._page(plot), plot.title)
            if plot.title == current:
                self.tabs.setCurrentIndex(self.tabs.count() - 1)
        self._show_pictures((pictures, size))
        self.refreshed.emit()

    def _show_pictures(self, drawn: tuple[dict[str, np.ndarray], tuple[int, int, float]]) -> None:
        pictures, size = drawn
        for k in range(self.tabs.count()):
            page = self.tabs.widget(k)
            rgba = pictures.get(page.objectName().removeprefix("plot-"))
            if rgba is not None:
                page.findChild(FigurePicture).set_picture(rgba, size[2])
        self._drawn_at = size

    def _page(self, plot: Plot) -> QWidget:
        page = QWidget()
        page.setObjectName(f"plot-{plot.name}")
        layout = QVBoxLayout(page)
        layout.setContentsMargins(PAGE_MARGIN, PAGE_MARGIN, PAGE_MARGIN, PAGE_MARGIN)
        layout.setSpacing(PAGE_MARGIN)
        if plot.figure is None:
            reason = QLabel(f"Not available: {plot.reason}")
            reason.setObjectName("plot-reason")
            reason.setWordWrap(True)
            reason.setAlignment(Qt.AlignmentFlag.AlignCenter)
            layout.addWidget(reason)
            return page
        picture = FigurePicture()
        picture.resized.connect(self._resize_timer.start)
        layout.addWidget(picture, 1)
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
            page.setParent(None)  # a removed tab stays the tabs' child until deleted: not found by name
            page.deleteLater()
        self.plots = {}
        self.out_of_date.hide()

    # -- exporting ------------------------------------------------------------------------------------

    def export_image(self, name: str, path: str | Path) -> None:
        """Save the figure of plot `name` as PNG or SVG (by the suffix of `path`)."""
        def save() -> None:
            with self._figures:  # waits for a worker drawing it (a fraction of a second)
                save_figure(self.plots[name].figure, path)

        self._export(f"Exporting the {name} plot", save, path)

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


class FigurePicture(QWidget):
    """A figure drawn by a worker, shown as a picture; scaled (aspect kept) until drawn at a new size."""

    resized = Signal()

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        self.setMinimumSize(*MIN_CANVAS)
        self.image = QImage()

    def set_picture(self, rgba: np.ndarray, pixel_ratio: float) -> None:
        h, w, _ = rgba.shape
        self.image = QImage(rgba.data, w, h, 4 * w, QImage.Format.Format_RGBA8888).copy()
        self.image.setDevicePixelRatio(pixel_ratio)
        self.update()

    def set_image(self, image: QImage) -> None:
        """Show a picture already drawn (a figure read from its file)."""
        self.image = image
        self.update()

    def sizeHint(self) -> QSize:
        return QSize(*MIN_CANVAS)

    def resizeEvent(self, _event) -> None:
        self.resized.emit()

    def paintEvent(self, _event) -> None:
        painter = QPainter(self)
        painter.fillRect(self.rect(), QColor("white"))
        if self.image.isNull():
            return
        shown = self.image.deviceIndependentSize().scaled(self.size().toSizeF(), Qt.AspectRatioMode.KeepAspectRatio)
        corner = (self.size().toSizeF() - shown) / 2
        painter.setRenderHint(QPainter.RenderHint.SmoothPixmapTransform)
        painter.drawImage(QRectF(corner.width(), corner.height(), shown.width(), shown.height()), self.image)


def _remedy(stale: tuple[str, ...]) -> str:
    """What brings out-of-date results up to date: new sets change the lengths per set, so Analyse follows Orient."""
    steps = []
    if {"sets", "density_peaks"} & set(stale):
        steps.append("Analysis → Orient traces…")
    if steps or {"topology", "lengths"} & set(stale):
        steps.append("Analysis → Analyse terminations and lengths…")
    if "intensity" in stale:
        steps.append("Compute in the Intensity maps panel")
    return ", then ".join(steps)


def _read_build_and_draw(project: Project, traces: list[Trace3D], scanlines: list[ScanlineMeasure],
                         windows: list[WindowMeasure], similarity: Similarity | None, size: tuple[int, int, float], lock: threading.Lock, *,
                         progress: Progress
                         ) -> tuple[dict[str, Plot], dict[str, np.ndarray], tuple[int, int, float], tuple[str, ...]]:
    """The plots of `project` (with the session's `traces`) and of the `scanlines` and scan circles
    (`windows`, in the frame of `similarity`), their pictures at `size`, and the stored results they show that are out of date (runs on a worker, reading through its own connection).

    The figures this build replaces are cycles of about 21,000 objects, freed only by the garbage collector.
    They are swept first, one set at a time (25–60 ms of the GIL): a full collection left to itself waits
    until several sets have piled up and held the GIL 60–190 ms, which froze the window (session 15)."""
    gc.collect()
    report(progress, 0.0, "reading the plot data")
    handle = project.for_thread()
    try:
        data = plot_data(handle, traces)
    finally:
        handle.close()
    plots = build_plots(data, progress=lambda f, m: report(progress, 0.1 + 0.5 * f, m))
    plots.update((plot.name, plot) for plot in (scanline_plot(m, similarity) for m in scanlines))
    if windows:
        plots["scan_circles"] = scan_circle_plot(windows, similarity)
    pictures, _ = _draw_all(plots, size, lock, progress=lambda f, m: report(progress, 0.6 + 0.4 * f, m))
    return plots, pictures, size, data.out_of_date


def _draw_all(plots: dict[str, Plot], size: tuple[int, int, float], lock: threading.Lock, *,
              progress: Progress) -> tuple[dict[str, np.ndarray], tuple[int, int, float]]:
    """Each figure drawn at `size` (logical width, height, device pixel ratio) as RGBA (runs on a worker)."""
    pictures = {}
    figures = {name: plot.figure for name, plot in plots.items() if plot.figure is not None}
    for k, (name, figure) in enumerate(figures.items()):
        report(progress, k / len(figures), f"drawing {name.replace('_', ' ')}")
        with lock:
            pictures[name] = _draw(figure, size)
    return pictures, size


def _draw(figure: Figure, size: tuple[int, int, float]) -> np.ndarray:
    """The figure drawn as a Qt canvas of that size would draw it: at the screen's dpi, its layout redone."""
    width, height, ratio = size
    dpi = mpl.rcParams["figure.dpi"]
    canvas = FigureCanvasAgg(figure)
    figure.set_dpi(dpi * ratio)
    figure.set_size_inches(width / dpi, height / dpi)
    canvas.draw()
    return np.array(canvas.buffer_rgba())  # a copy: the canvas's buffer is reused by the next draw
