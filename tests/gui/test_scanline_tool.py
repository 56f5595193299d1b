"""The 3D viewer's Scanline tool, clicked: two clicks on a wall lay a scanline across traces 1 m apart, which
is measured, stored, listed, drawn, undone, redone and removed; quick clicks are taken in order; a click off
the rock is told; a change of the traces measures the scanlines again; readouts follow the registration."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from engine.project import Project
from engine.render import SCANLINE_ACTORS, SCANLINE_COLOR
from tests.gui.flows import actor_data, open_viewer, register
from tests.gui.test_facet_tool import click_at
from tests.gui.test_merge_tool import colour_share
from tests.scenes import facing_camera, grid_wall
from tests.test_scanline import vertical_traces
from tracemap_gui.scanline_tool import START_ACTOR
from tracemap_gui.session import Session

WEST_END, EAST_END = np.array([0.5, 0.0, 3.0]), np.array([9.5, 0.0, 3.0])  # mesh file coordinates


@pytest.fixture
def viewer(tmp_path, qtbot):
    v, f = grid_wall(step=0.25)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "wall.ply")
    with Project.create(tmp_path / "wall.tracemap", mesh_path=tmp_path / "wall.ply",
                        cameras={"left": facing_camera("left")}) as project:
        project.add_traces3d(vertical_traces(np.arange(1.0, 9.5, 1.0), offset=-project.origin))
    session = Session()
    session.open(tmp_path / "wall.tracemap")
    window = open_viewer(qtbot, session)
    qtbot.waitUntil(lambda: window.mesh is not None, timeout=20000)
    centre = np.array([5.0, 0.0, 3.0]) - session.project.origin
    window.view.plotter.camera_position = [tuple(centre + [0.0, -14.0, 0.0]), tuple(centre), (0.0, 0.0, 1.0)]
    window.view.refresh()
    yield window
    session.jobs.cancel_all(5000)
    session.close()


def lay(window, qtbot, start, end):
    """Click both ends and wait for the scanline laid between them (or None)."""
    with qtbot.waitSignal(window.scanline_tool.laid, timeout=60_000) as laid:
        click_at(window, qtbot, start)
        click_at(window, qtbot, end)  # at once: the first pick may still be running
    return laid.args[0]


def test_two_clicks_lay_a_scanline_that_is_measured_stored_drawn_and_undone(viewer, qtbot, tmp_path):
    tool = viewer.scanline_tool
    click_at(viewer, qtbot, WEST_END)
    assert tool.start is None  # the tool is off: clicks select traces
    tool.action.trigger()
    tool.name.setText("level")
    measure = lay(viewer, qtbot, WEST_END, EAST_END)
    assert measure is not None and measure.all.n == 9
    origin = viewer.session.project.origin
    assert np.linalg.norm(measure.line.start + origin - WEST_END) < 0.02  # picked where clicked
    np.testing.assert_allclose(measure.sets[0].spacing, 1.0, atol=0.01)
    (stored,) = viewer.session.project.scanlines()
    assert stored.name == "level" and stored.id == measure.line.id
    qtbot.waitUntil(lambda: tool.list.count() == 1 and stored.id in tool.measures, timeout=20000)
    assert tool.list.item(0).text().startswith(f"{stored.id} (level): ") and "9 crossings" in tool.list.item(0).text()
    assert tool.reports()[stored.id]["length_m"] == pytest.approx(9.0, abs=0.05)  # clicked within a pixel
    assert "set 0: 9 traces" in tool.details.toPlainText()
    assert actor_data(viewer.view.plotter.actors[SCANLINE_ACTORS[1]]).n_points == 9
    assert SCANLINE_ACTORS[0] in viewer.view.plotter.actors and START_ACTOR not in viewer.view.plotter.actors
    qtbot.waitUntil(lambda: colour_share(viewer, SCANLINE_COLOR) > 1e-3, timeout=20000)  # in the frames drawn

    viewer.session.undo_stack.undo()
    assert viewer.session.project.scanlines() == [] and tool.list.count() == 0
    assert SCANLINE_ACTORS[0] not in viewer.view.plotter.actors
    viewer.session.undo_stack.redo()
    assert [s.id for s in viewer.session.project.scanlines()] == [stored.id]
    qtbot.waitUntil(lambda: tool.list.count() == 1 and stored.id in tool.measures, timeout=20000)

    panel = viewer.plots_panel  # a tab of the scanline's cumulative crossings beside the analysis plots
    qtbot.waitUntil(lambda: f"scanline_{stored.id}" in panel.plots, timeout=30000)
    assert f"Scanline {stored.id}" in [panel.tabs.tabText(k) for k in range(panel.tabs.count())]
    assert panel.plots[f"scanline_{stored.id}"].table.rows[-1][2] == 9
    tool.list.setCurrentRow(0)
    tool.export_plot(tmp_path / "level.png")
    assert (tmp_path / "level.png").stat().st_size > 10_000 and "saved" in tool.message.text()
    assert (tmp_path / "level.csv").read_text().count("set 0") == 9
    tool.remove_button.click()
    assert viewer.session.project.scanlines() == [] and tool.list.count() == 0
    viewer.session.undo_stack.undo()
    assert [s.id for s in viewer.session.project.scanlines()] == [stored.id]


def test_a_click_off_the_rock_is_told_and_the_next_two_lay_a_scanline(viewer, qtbot):
    tool = viewer.scanline_tool
    tool.action.trigger()
    click_at(viewer, qtbot, np.array([5.0, 0.0, 9.0]))  # the sky above the wall
    qtbot.waitUntil(lambda: "no mesh under the cursor" in tool.message.text(), timeout=20000)
    assert tool.start is None
    click_at(viewer, qtbot, WEST_END)
    qtbot.waitUntil(lambda: tool.start is not None, timeout=20000)
    assert START_ACTOR in viewer.view.plotter.actors and "other end" in tool.message.text()
    with qtbot.waitSignal(tool.laid, timeout=60_000) as laid:
        click_at(viewer, qtbot, EAST_END)
    assert laid.args[0].all.n == 9


def test_scanlines_are_measured_again_when_the_traces_change(viewer, qtbot):
    tool = viewer.scanline_tool
    tool.action.trigger()
    line = lay(viewer, qtbot, WEST_END, EAST_END).line
    qtbot.waitUntil(lambda: line.id in tool.measures, timeout=20000)
    rock = tool.measures[line.id].rock
    first = viewer.session.traces3d()[0]
    with qtbot.waitSignal(tool.measured, timeout=20000):
        viewer.session.select3d([first.id])
        viewer.delete_action.trigger()
    assert tool.measures[line.id].all.n == 8 and "8 crossings" in tool.list.item(0).text()
    assert tool.measures[line.id].rock is rock  # the mesh and the line did not change: nor did the rock under it


def test_readouts_and_the_reach_are_in_the_registered_frame(viewer, qtbot):
    tool = viewer.scanline_tool
    register(viewer.session.project, 2.0)
    viewer.session.registration_changed.emit()
    tool.action.trigger()
    tool.reach.setValue(1.0)  # metres of the GCPs' frame: 0.5 m on the mesh
    measure = lay(viewer, qtbot, WEST_END, EAST_END)
    assert measure.line.reach == pytest.approx(0.5)
    qtbot.waitUntil(lambda: tool.list.count() == 1 and measure.line.id in tool.measures, timeout=20000)
    report = tool.reports()[measure.line.id]
    assert report["length_m"] == pytest.approx(18.0, abs=0.1) and report["reach_m"] == pytest.approx(1.0)
    assert report["groups"]["all"]["p10_per_m"] == pytest.approx(9 / report["sampled_m"])
    assert "spacing mean 2.00 m" in tool.details.toPlainText()


def test_lay_levels_stores_a_survey_in_one_edit_and_reads_it_pooled(viewer, qtbot):
    tool = viewer.scanline_tool
    tool.levels.setValue(3)
    tool.name.setText("bench")
    with qtbot.waitSignal(tool.surveyed, timeout=60_000) as surveyed:
        tool.levels_button.click()
    stored = surveyed.args[0]
    assert [m.line.name for m in stored] == ["bench 1", "bench 2", "bench 3"]
    assert [m.all.n for m in stored] == [9, 9, 9]  # the traces run from 0.5 to 5.5 m; the levels at 1, 3, 5 m
    qtbot.waitUntil(lambda: len(tool.measures) == 3 and tool.list.count() == 3, timeout=20000)
    tool.list.setCurrentRow(1)
    assert "all 3 scanlines: " in tool.details.toPlainText() and "27 crossings" in tool.details.toPlainText()
    viewer.session.undo_stack.undo()  # one edit
    assert viewer.session.project.scanlines() == []
