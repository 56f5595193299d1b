import gc
import sqlite3

import numpy as np
import pytest
from matplotlib.collections import PathCollection
from matplotlib.figure import Figure
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QLabel, QMainWindow, QPushButton

from engine.plots import equal_area
from tracemap_gui.commands import EditTraces3D, ReplaceTraces3D
from tracemap_gui.plots_panel import PlotsPanel

TITLES = ["Poles to fracture traces", "Trace lengths", "Kaplan–Meier survival of trace lengths",
          "Terminations and topology", "Abutting and crossing between sets", "Summary"]


def shown_panel(qtbot, session):
    window = QMainWindow()
    qtbot.addWidget(window)
    panel = PlotsPanel(session, window)
    window.addDockWidget(Qt.DockWidgetArea.BottomDockWidgetArea, panel)
    window.resize(900, 700)
    with qtbot.waitSignal(panel.refreshed, timeout=30_000):
        window.show()
    return window, panel


@pytest.fixture
def panel(qtbot, session):
    window, panel = shown_panel(qtbot, session)
    yield panel
    session.jobs.cancel_all()
    qtbot.waitUntil(lambda: not session.jobs.running, timeout=30_000)


def page(panel, name):
    return panel.tabs.findChild(type(panel.tabs.widget(0)), f"plot-{name}")


def rows(panel, name, kind):
    return [r for r in panel.plots[name].table.rows if r[0] == kind]


def test_panel_shows_every_plot_of_the_project(panel, qtbot):
    assert [panel.tabs.tabText(k) for k in range(panel.tabs.count())] == TITLES
    oriented = [t for t in panel.session.traces3d() if t.normal is not None]
    scatter = next(c for c in panel.plots["stereonet"].figure.axes[0].collections if isinstance(c, PathCollection))
    np.testing.assert_allclose(scatter.get_offsets(), equal_area(np.array([t.normal for t in oriented])))
    # the canvas really draws the figure: dark pole markers and contours on white
    panel.tabs.setCurrentIndex(0)
    qtbot.waitUntil(lambda: page(panel, "stereonet").isVisible())
    image = page(panel, "stereonet").grab().toImage()
    dark = sum(image.pixelColor(x, y).lightness() < 100 for x in range(0, image.width(), 4)
               for y in range(0, image.height(), 4))
    assert dark > 50


def test_plots_follow_trace_edits_and_undo(panel, qtbot, session):
    trace = next(t for t in session.traces3d() if t.normal is not None and t.term_start == "B")
    n_poles = len(rows(panel, "stereonet", "pole"))
    t_count = dict(panel.plots["terminations"].table.rows)["T"]
    assert not panel.out_of_date.isVisibleTo(panel)  # the stored analysis is of these traces
    with qtbot.waitSignal(panel.refreshed, timeout=30_000):
        session.push(EditTraces3D.setting(session, [trace], "Set start node to T", term_start="T"))
    assert dict(panel.plots["terminations"].table.rows)["T"] == t_count + 1
    # node counts and lengths were analysed with the old end code: the panel says so
    assert panel.out_of_date.isVisibleTo(panel) and "topology, lengths" in panel.out_of_date.text()
    with qtbot.waitSignal(panel.refreshed, timeout=30_000):
        session.push(ReplaceTraces3D(session, [next(t for t in session.traces3d() if t.id == trace.id)], [],
                                     "Delete 1 3D trace"))
    assert len(rows(panel, "stereonet", "pole")) == n_poles - 1
    assert trace.id not in [r[1] for r in rows(panel, "stereonet", "pole")]
    assert rows(panel, "summary", "all traces")[0][1] == len(session.traces3d())
    with qtbot.waitSignal(panel.refreshed, timeout=30_000):
        session.undo_stack.undo()
        session.undo_stack.undo()
    assert len(rows(panel, "stereonet", "pole")) == n_poles
    assert dict(panel.plots["terminations"].table.rows)["T"] == t_count
    assert not panel.out_of_date.isVisibleTo(panel)


def test_replaced_figures_never_pile_up_for_the_garbage_collector(panel, qtbot, session):
    """A set of five figures is ~21,000 objects in cycles; a full collection of three sets held the GIL up to
    0.19 s. Each rebuild sweeps the set the last one replaced, so at most one old set waits, even with the
    automatic collector off."""
    trace = next(t for t in session.traces3d() if t.normal is not None)
    gc.collect()
    gc.disable()
    try:
        for k in range(3):
            with qtbot.waitSignal(panel.refreshed, timeout=30_000):
                session.push(EditTraces3D.setting(session, [trace], f"Set {k}", set_id=k + 1))
        figures = sum(isinstance(o, Figure) for o in gc.get_objects())
    finally:
        gc.enable()
    assert figures <= 2 * len(TITLES), figures


def test_a_hidden_panel_builds_nothing_until_shown(panel, qtbot, session):
    panel.hide()
    trace = session.traces3d()[0]
    session.push(ReplaceTraces3D(session, [trace], [], "Delete 1 3D trace"))
    qtbot.wait(600)  # longer than the debounce
    assert not session.jobs.running
    assert rows(panel, "summary", "all traces")[0][1] == len(session.traces3d()) + 1  # still the old plots
    with qtbot.waitSignal(panel.refreshed, timeout=30_000):
        panel.show()
    assert rows(panel, "summary", "all traces")[0][1] == len(session.traces3d())


def test_export_buttons_write_the_figure_and_its_data(panel, qtbot, tmp_path, monkeypatch):
    answers = iter([(str(tmp_path / "poles.svg"), "SVG image (*.svg)"), (str(tmp_path / "km"), "PNG image (*.png)"),
                    (str(tmp_path / "poles"), "CSV table (*.csv)")])
    monkeypatch.setattr("tracemap_gui.plots_panel.QFileDialog.getSaveFileName", lambda *a, **k: next(answers))
    panel.tabs.setCurrentIndex(0)
    stereonet = page(panel, "stereonet")
    qtbot.mouseClick(stereonet.findChild(QPushButton, "export-image"), Qt.MouseButton.LeftButton)
    assert "<svg" in (tmp_path / "poles.svg").read_text(encoding="utf-8")
    panel.tabs.setCurrentIndex(2)
    qtbot.mouseClick(page(panel, "kaplan_meier").findChild(QPushButton, "export-image"), Qt.MouseButton.LeftButton)
    assert (tmp_path / "km.png").read_bytes()[:4] == b"\x89PNG"  # suffix added from the chosen filter
    panel.tabs.setCurrentIndex(0)
    qtbot.mouseClick(stereonet.findChild(QPushButton, "export-table"), Qt.MouseButton.LeftButton)
    lines = (tmp_path / "poles.csv").read_text(encoding="utf-8").splitlines()
    assert lines[0] == "kind,id,set,dip,dip_direction,x,y"
    assert len(lines) - 1 == len(panel.plots["stereonet"].table.rows)
    assert float(lines[1].split(",")[3]) == panel.plots["stereonet"].table.rows[0][3]


def test_a_plot_without_its_analysis_says_why(qtbot, project_path):
    from tracemap_gui.session import Session

    with sqlite3.connect(project_path) as db:  # as before `tracemap analyse`
        db.execute("DELETE FROM results WHERE name IN ('topology', 'lengths')")
    session = Session()
    session.open(project_path)
    try:
        _, panel = shown_panel(qtbot, session)
        reason = page(panel, "terminations").findChild(QLabel, "plot-reason")
        assert "run `tracemap analyse`" in reason.text()
        assert page(panel, "terminations").findChild(QPushButton, "export-image") is None
        assert len(panel.plots["length_histogram"].figure.axes[0].lines) == 0  # bars, but no fits yet
    finally:
        session.close()


def test_the_3d_viewer_has_the_plots_dock(qtbot, session):
    from tracemap_gui.viewer3d import Viewer3D

    viewer = Viewer3D(session, offscreen=True)
    qtbot.addWidget(viewer)
    with qtbot.waitSignal(viewer.plots_panel.refreshed, timeout=30_000):
        viewer.show()
    assert viewer.plots_panel.toggleViewAction() in viewer.view_menu.actions()
    assert viewer.dockWidgetArea(viewer.plots_panel) == Qt.DockWidgetArea.BottomDockWidgetArea
    tabs = viewer.plots_panel.tabs
    scanlines = session.project.scanlines()  # the demo lays one: its tab follows once it is measured
    assert len(scanlines) == 1
    qtbot.waitUntil(lambda: tabs.count() == len(TITLES) + 1, timeout=30_000)
    assert [tabs.tabText(k) for k in range(tabs.count())] == [*TITLES, f"Scanline {scanlines[0].id}"]
    qtbot.waitUntil(lambda: not session.jobs.running, timeout=30_000)


def test_figures_are_drawn_on_a_worker_and_again_after_a_resize(panel, qtbot, session, monkeypatch):
    """Drawing the figures takes ~1 s: the GUI thread only shows the pictures (issue 5)."""
    import threading

    from matplotlib.figure import Figure

    from tracemap_gui.plots_panel import FigurePicture

    drawn_on = []
    draw = Figure.draw
    monkeypatch.setattr(Figure, "draw", lambda fig, renderer: drawn_on.append(threading.current_thread())
                        or draw(fig, renderer))
    trace = session.traces3d()[0]
    with qtbot.waitSignal(panel.refreshed, timeout=30_000):
        session.push(ReplaceTraces3D(session, [trace], [], "Delete 1 3D trace"))
    assert len(drawn_on) >= sum(p.figure is not None for p in panel.plots.values()) >= 4
    assert threading.main_thread() not in drawn_on
    panel.tabs.setCurrentIndex(0)
    picture = page(panel, "stereonet").findChild(FigurePicture)
    old = picture.image.size()
    panel.window().resize(1100, 800)
    qtbot.waitUntil(lambda: picture.width() > 1000)
    qtbot.waitUntil(lambda: picture.image.width() == round(picture.width() * picture.devicePixelRatioF())
                    and picture.image.height() == round(picture.height() * picture.devicePixelRatioF()),
                    timeout=30_000)
    assert picture.image.width() > old.width() and threading.main_thread() not in drawn_on


def test_plot_data_is_read_on_a_worker_and_a_failure_keeps_the_old_plots(panel, qtbot, session, monkeypatch):
    """Reading the maps' blobs took the GUI thread 20–70 ms (issue 5): the worker reads through its own
    connection; if reading fails the user is told and the plots shown stay."""
    import threading

    from PySide6.QtWidgets import QMessageBox

    from engine.errors import ProjectError
    from tracemap_gui import plots_panel

    read_on = []
    read = plots_panel.plot_data

    def recording(project, traces):
        read_on.append((threading.current_thread(), project is session.project))
        return read(project, traces)

    monkeypatch.setattr(plots_panel, "plot_data", recording)
    with qtbot.waitSignal(panel.refreshed, timeout=30_000):
        panel.refresh()
    assert read_on == [(read_on[0][0], False)] and read_on[0][0] is not threading.main_thread()

    shown = panel.plots
    monkeypatch.setattr(plots_panel, "plot_data", lambda project, traces: (_ for _ in ()).throw(
        ProjectError("demo.tracemap: the results table is damaged")))
    panel.refresh()
    qtbot.waitUntil(lambda: bool(panel.findChildren(QMessageBox)), timeout=30_000)
    box = next(b for b in panel.findChildren(QMessageBox) if b.objectName() == "error-dialog")
    assert "results table is damaged" in box.informativeText()
    assert panel.plots is shown and panel.tabs.count() == len(TITLES)
    box.close()


def test_a_new_refresh_cancels_the_one_running(panel, qtbot, session):
    shown = []
    panel.refreshed.connect(lambda: shown.append(panel.plots))
    panel.refresh()
    first = panel._task
    panel.refresh()
    assert first._cancel.is_set() and panel._task is not first
    qtbot.waitUntil(lambda: not session.jobs.running, timeout=30_000)
    assert len(shown) == 1  # only the latest refresh's plots are shown
