"""File → Analyse a 2D map…: the form, the analysis on a worker, its figures and summary, failures said."""

from __future__ import annotations

import json
import re

import pytest

from tests.gui.test_app import dialog_text, gui  # noqa: F401 - the application fixture
from tests.test_maps2d import HOLE, SHELL, _write, random_network
from tracemap_gui.map_window import MapForm, MapRequest, MapWindow


@pytest.fixture
def geojson_map(tmp_path):
    lines, sets = random_network(5, n1=25, n2=35)
    (traces, area), *_ = _write(tmp_path, lines, sets, [[SHELL, HOLE]], "GeoJSON", ".geojson")
    return traces, area


def _window(qtbot) -> MapWindow:
    window = MapWindow()
    qtbot.addWidget(window)
    window.show()
    return window


def _run(qtbot, window: MapWindow, request: MapRequest) -> list:
    ended = []
    task = window.run(request)
    for signal in (task.signals.done, task.signals.failed):
        signal.connect(ended.append)
    qtbot.waitUntil(lambda: bool(ended), timeout=120_000)
    return ended


def test_the_form_names_what_is_wrong(qtbot, tmp_path, geojson_map):
    traces, area = geojson_map
    form = MapForm()
    qtbot.addWidget(form)

    def refused(message):
        with pytest.raises(Exception, match=re.escape(message)):
            form.parse()

    refused("Traces: expected the file of the trace LineStrings; none given")
    form.traces.edit.setText(str(tmp_path / "nowhere.geojson"))
    refused("nowhere.geojson: Traces: no such file")
    form.traces.edit.setText(str(traces))
    refused("Sampling area: expected the file of the polygon of the mapped area")
    form.area.edit.setText(str(area))
    refused("Output folder: expected where to write the tables and figures")
    form.output.edit.setText(str(traces))
    refused("Output folder: is a file")
    form.output.edit.setText(str(tmp_path / "out"))
    form.grid_radius.setValue(30)
    refused("P21 disc radius: the map's discs need a P21 map cell")
    form.grid.setValue(20)
    form.circles.setText("50 50 10; 20 70")
    refused("Scan circles: expected 'x y r' for each circle, separated by ';'; got '20 70'")
    form.circles.setText("50 50 -1")
    refused("Scan circles: expected a radius above 0")
    form.circles.setText("500050, 6700050, 10; 500020 6700070 5;")
    form.set_column.setText(" set ")
    assert form.parse() == MapRequest(traces, area, tmp_path / "out", grid=20.0, grid_radius=30.0,
                                      scan_circles=((500050.0, 6700050.0, 10.0), (500020.0, 6700070.0, 5.0)),
                                      set_column="set")
    assert form.grid.text() == "20" and MapForm().grid.text() == "none"  # 0: no P21 map
    assert form.snap.text() == "0.001"
    form.snap.lineEdit().setText("0.25")
    form.snap.interpretText()
    assert form.snap.value() == 0.25


def test_a_map_is_analysed_in_the_background(qtbot, tmp_path, geojson_map):
    traces, area = geojson_map
    window = _window(qtbot)
    out = tmp_path / "out"
    [output] = _run(qtbot, window, MapRequest(traces, area, out, n_bootstrap=9, grid=20.0))
    assert output is window.output
    titles = [window.tabs.tabText(k) for k in range(window.tabs.count())]
    assert titles == [plot.title for plot in output.plots.values()] + ["Summary"]
    assert len(titles) == 9  # map, lengths, Kaplan–Meier, terminations, rose, relations, P21 and C_B maps, summary
    for k in range(window.tabs.count() - 1):
        picture = window.tabs.widget(k)
        assert not picture.image.isNull() and picture.image.width() > 400  # the PNG written, read back
    written = sorted(p.name for p in out.iterdir())
    assert written == sorted(f.name for f in output.files) and "p21_grid.png" in written
    # the summary says what summary.json holds
    stored = json.loads((out / "summary.json").read_text())
    text = window.tabs.widget(window.tabs.count() - 1).toPlainText()
    nodes = stored["nodes"]
    assert f"{stored['traces_in_area']} traces in the area" in text
    assert f"nodes {nodes['N_I']} I, {nodes['N_Y']} Y, {nodes['N_X']} X, {nodes['N_E']} E" in text
    assert "lengths, set 1:" in text and "lengths, set 2:" in text and "P21 map" in text
    assert window.statusBar().currentMessage() == f"wrote {len(output.files)} files to {out}"
    assert window.form.run.isEnabled()


def test_a_map_that_cannot_be_analysed_is_said_and_nothing_written(qtbot, tmp_path, geojson_map):
    traces, _ = geojson_map
    window = _window(qtbot)
    out = tmp_path / "out"
    [exc] = _run(qtbot, window, MapRequest(traces, traces, out, n_bootstrap=0))  # lines given as the area
    text = dialog_text(window)
    assert f"Analysing {traces} failed" in text and str(traces) in text and "Polygon" in text
    assert "Traceback" not in text and not out.exists()


def test_the_form_is_kept_for_next_time(qtbot, tmp_path, geojson_map):
    traces, area = geojson_map
    window = _window(qtbot)
    window.form.traces.edit.setText(str(traces))
    window.form.run.click()
    assert "Sampling area: expected" in window.form.message.text() and not window.jobs.running
    window.form.area.edit.setText(str(area))
    window.form.output.edit.setText(str(tmp_path / "out"))
    window.form.bootstrap.setValue(0)
    window.form.circle_grid.setValue(12.5)
    task = window.run_form()
    assert task is not None and window.form.message.text() == "" and not window.form.run.isEnabled()
    qtbot.waitUntil(lambda: window.output is not None, timeout=120_000)
    assert "scan circle grid: " in window.tabs.widget(window.tabs.count() - 1).toPlainText()
    again = _window(qtbot)
    assert again.form.state() == window.form.state() and again.form.parse() == window.form.parse()


def test_the_file_menu_opens_one_map_window_without_a_project(gui, qtbot):  # noqa: F811
    assert "Analyse a 2D &map…" in [a.text() for a in gui.editor.file_menu.actions()]
    assert not gui.session.is_open
    window = gui.show_map_window()
    qtbot.addWidget(window)
    assert window.isVisible() and window.windowTitle() == "tracemap: 2D map"
    assert gui.show_map_window() is window


def test_a_cancelled_analysis_writes_nothing(qtbot, tmp_path, geojson_map):
    traces, area = geojson_map
    window = _window(qtbot)
    out = tmp_path / "out"
    task = window.run(MapRequest(traces, area, out, n_bootstrap=0))
    cancelled = []
    task.signals.cancelled.connect(lambda: cancelled.append(True))
    task.cancel()  # as the status bar's Cancel does: the analysis stops at its next progress report
    qtbot.waitUntil(lambda: bool(cancelled), timeout=60_000)
    assert not out.exists() and window.output is None
    assert window.statusBar().currentMessage() == "analysis cancelled"
