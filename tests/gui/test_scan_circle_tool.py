"""The 3D viewer's Scan circle tool, clicked: a click on a wall of vertical traces 1 m apart lays a window,
which is measured, stored, listed, drawn, undone, redone and removed; a click off the rock is told; a change
of the traces measures the windows again on the same rock; readouts follow the registration; Lay grid stores
a grid of windows in one edit and reads them pooled."""

from __future__ import annotations

import numpy as np
import pytest

from engine.render import WINDOW_ACTORS, WINDOW_COLOR
from tests.gui.flows import actor_data, register
from tests.gui.test_facet_tool import click_at
from tests.gui.test_merge_tool import colour_share
from tests.gui.test_scanline_tool import viewer  # noqa: F401 - the wall of vertical traces 1 m apart, face on

MIDDLE = np.array([5.0, 0.0, 3.0])  # mesh file coordinates


def lay(window, qtbot, centre):
    """Click the centre and wait for the window laid round it (a list of one measure, or None)."""
    with qtbot.waitSignal(window.scan_circle_tool.laid, timeout=60_000) as laid:
        click_at(window, qtbot, centre)
    return laid.args[0]


def test_a_click_lays_a_window_that_is_measured_stored_drawn_and_undone(viewer, qtbot):  # noqa: F811
    tool = viewer.scan_circle_tool
    tool.action.trigger()
    tool.radius.setValue(1.5)
    tool.name.setText("middle")
    (measure,) = lay(viewer, qtbot, MIDDLE)
    origin = viewer.session.project.origin
    assert np.linalg.norm(measure.circle.centre + origin - MIDDLE) < 0.02  # picked where clicked
    # the traces at x 4, 5 and 6 run through it top to bottom: two cuts each, no end inside
    assert (measure.counts.cuts, measure.counts.ends, measure.circle.radius) == (6, 0, 1.5)
    (stored,) = viewer.session.project.scan_circles()
    assert stored.name == "middle" and stored.id == measure.circle.id and tool.name.text() == ""
    qtbot.waitUntil(lambda: tool.list.count() == 1 and stored.id in tool.measures, timeout=20000)
    assert tool.list.item(0).text().startswith(f"{stored.id} (middle): r 1.5 m, 6 cuts, 0 ends, P21 1.00")  # n/4r
    assert "6 edge cuts, 0 trace ends inside" in tool.details.toPlainText()
    assert actor_data(viewer.view.plotter.actors[WINDOW_ACTORS[1]]).n_points == 6
    assert WINDOW_ACTORS[0] in viewer.view.plotter.actors and WINDOW_ACTORS[2] not in viewer.view.plotter.actors
    # drawn in the frames the render thread makes, not only in the scene (cell-coloured tubes were not)
    qtbot.waitUntil(lambda: colour_share(viewer, WINDOW_COLOR) > 1e-3, timeout=20000)

    viewer.session.undo_stack.undo()
    assert viewer.session.project.scan_circles() == [] and tool.list.count() == 0
    assert WINDOW_ACTORS[0] not in viewer.view.plotter.actors
    viewer.session.undo_stack.redo()
    assert [c.id for c in viewer.session.project.scan_circles()] == [stored.id]
    qtbot.waitUntil(lambda: tool.list.count() == 1 and stored.id in tool.measures, timeout=20000)
    tool.list.setCurrentRow(0)
    tool.remove_button.click()
    assert viewer.session.project.scan_circles() == [] and tool.list.count() == 0
    viewer.session.undo_stack.undo()
    assert [c.id for c in viewer.session.project.scan_circles()] == [stored.id]


def test_a_click_off_the_rock_is_told_and_ends_inside_are_marked(viewer, qtbot):  # noqa: F811
    tool = viewer.scan_circle_tool
    tool.action.trigger()
    assert lay(viewer, qtbot, np.array([5.0, 0.0, 9.0])) is None  # the sky above the wall
    assert "no mesh under the cursor" in tool.message.text()
    tool.radius.setValue(0.8)
    (measure,) = lay(viewer, qtbot, np.array([5.0, 0.0, 5.2]))  # round the top end of the trace at x 5
    assert (measure.counts.cuts, measure.counts.ends) == (1, 1) and "stored: " in tool.message.text()
    qtbot.waitUntil(lambda: measure.circle.id in tool.measures, timeout=20000)
    assert actor_data(viewer.view.plotter.actors[WINDOW_ACTORS[2]]).n_points == 1
    assert viewer.session.setting("scan_circle/radius") == pytest.approx(0.8)  # a new window's, kept


def test_windows_are_measured_again_when_the_traces_change(viewer, qtbot):  # noqa: F811
    tool = viewer.scan_circle_tool
    tool.action.trigger()
    tool.radius.setValue(1.5)
    (measure,) = lay(viewer, qtbot, MIDDLE)
    qtbot.waitUntil(lambda: measure.circle.id in tool.measures, timeout=20000)
    rock = tool.measures[measure.circle.id].rock
    middle = next(t for t in viewer.session.traces3d() if abs(t.points[0, 0] + viewer.session.project.origin[0]
                                                                - 5.0) < 1e-6)
    with qtbot.waitSignal(tool.measured, timeout=20000):
        viewer.session.select3d([middle.id])
        viewer.delete_action.trigger()
    assert tool.measures[measure.circle.id].counts.cuts == 4 and "4 cuts" in tool.list.item(0).text()
    assert tool.measures[measure.circle.id].rock is rock  # the mesh and the circle did not change: nor its rock


def test_readouts_and_the_radius_are_in_the_registered_frame(viewer, qtbot):  # noqa: F811
    tool = viewer.scan_circle_tool
    register(viewer.session.project, 2.0)
    viewer.session.registration_changed.emit()
    tool.action.trigger()
    tool.radius.setValue(3.0)  # metres of the GCPs' frame: 1.5 m on the mesh
    (measure,) = lay(viewer, qtbot, MIDDLE)
    assert measure.circle.radius == pytest.approx(1.5)
    qtbot.waitUntil(lambda: measure.circle.id in tool.measures, timeout=20000)
    report = tool.reports()[measure.circle.id]
    assert report["radius_m"] == pytest.approx(3.0) and report["edge_m"] == pytest.approx(2 * measure.counts.perimeter)
    assert report["p21_per_m"] == pytest.approx(measure.counts.p21 / 2)
    assert "r 3 m: 6 edge cuts" in tool.details.toPlainText()


def test_lay_grid_stores_windows_in_one_edit_and_reads_them_pooled(viewer, qtbot):  # noqa: F811
    tool = viewer.scan_circle_tool
    tool.radius.setValue(1.0)
    tool.name.setText("grid")
    with qtbot.waitSignal(tool.laid, timeout=60_000) as laid:
        tool.grid_button.click()
    stored = laid.args[0]
    # the 10 × 6 m wall: centres 2 m apart, 1 m in from its edges: 5 along it, 3 rows
    assert len(stored) == 15 and [m.circle.name for m in stored[:2]] == ["grid 1", "grid 2"]
    assert not any(m.rock.open for m in stored)
    qtbot.waitUntil(lambda: len(tool.measures) == 15 and tool.list.count() == 15, timeout=20000)
    tool.list.setCurrentRow(3)
    cuts = sum(m.counts.cuts for m in stored)
    assert f"all 15 scan circles (" in tool.details.toPlainText() and f"{cuts} edge cuts" in tool.details.toPlainText()
    panel = viewer.plots_panel  # a tab of the windows on the face beside the analysis plots
    qtbot.waitUntil(lambda: "scan_circles" in panel.plots, timeout=30000)
    assert "Scan circles" in [panel.tabs.tabText(k) for k in range(panel.tabs.count())]
    assert len(panel.plots["scan_circles"].table.rows) == 15
    viewer.session.undo_stack.undo()  # one edit
    assert viewer.session.project.scan_circles() == []
