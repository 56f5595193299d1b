"""The 3D viewer's Facet tool, clicked: a facet on an exposed fracture face is previewed, accepted, undone,
redone and removed; a click on the outcrop face is rejected with the reason; stored facets are drawn; on a
mesh of 636k faces a click returns at once and the window keeps running while the facet is fitted."""

from __future__ import annotations

import time

import numpy as np
import pytest
import trimesh
from PySide6.QtCore import QPoint, Qt, QTimer

from engine.orientation import axial_angle
from engine.project import Project
from tests.gui.flows import QUARTER_TURN, actor_data, assert_responsive, open_viewer, register
from tests.scenes import facing_camera, stepped_wall
from tracemap_gui.facet_tool import PATCH_ACTOR
from tracemap_gui.session import Session

ON_STEP = np.array([4.0, -0.3, 1.5])  # the middle of the exposed face x = 4 (mesh file coordinates)
ON_WALL = np.array([2.0, 0.0, 1.5])


def step_viewer(tmp_path, qtbot, spacing: float = 0.1):
    """The viewer on a project of the stepped wall meshed every `spacing` m, looking at the step."""
    v, f = stepped_wall(spacing=spacing)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "step.ply")
    Project.create(tmp_path / "step.tracemap", mesh_path=tmp_path / "step.ply",
                   cameras={"cam": facing_camera(centre=(1.0, -6.0, 1.5))}).close()
    session = Session()
    session.open(tmp_path / "step.tracemap")
    window = open_viewer(qtbot, session)
    origin = session.project.origin
    # look at the step from the south-west, so both the exposed face and the wall beside it are in view
    window.view.plotter.camera_position = [tuple(ON_STEP - origin + [-4.0, -5.0, 1.0]), tuple(ON_STEP - origin),
                                           (0.0, 0.0, 1.0)]
    window.view.refresh()
    return window


@pytest.fixture
def viewer(tmp_path, qtbot):
    window = step_viewer(tmp_path, qtbot)
    yield window
    window.session.jobs.cancel_all(5000)
    window.session.close()


def click_at(window, qtbot, point):
    """A real left click on the canvas where the mesh-file point is drawn."""
    renderer = window.view.plotter.renderer
    renderer.SetWorldPoint(*(point - window.session.project.origin), 1.0)
    renderer.WorldToDisplay()
    x, y, _ = renderer.GetDisplayPoint()
    canvas = window.view._canvas
    qtbot.mouseClick(canvas, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                     QPoint(int(round(x)), canvas.height() - 1 - int(round(y))))


def fit_at(window, qtbot, point):
    """Click where the mesh-file point is drawn and wait for the facet fitted there (or None)."""
    with qtbot.waitSignal(window.facet_tool.fitted, timeout=60_000) as fitted:
        click_at(window, qtbot, point)
    return fitted.args[0]


def refit(window, qtbot, radius: float):
    """Set the radius and wait for the facet refitted around the same point."""
    with qtbot.waitSignal(window.facet_tool.fitted, timeout=60_000) as fitted:
        window.facet_tool.radius.setValue(radius)
    return fitted.args[0]


def changed_pixels(window, before: np.ndarray) -> int:
    """How many pixels of the view differ clearly from `before` (the highlighted patch and its disc)."""
    return int(np.sum(np.abs(window.view.frame().astype(int) - before).sum(axis=-1) > 60))


def test_click_on_the_exposed_face_previews_then_accept_undo_redo_remove(viewer, qtbot):
    tool = viewer.facet_tool
    tool.radius.setValue(0.25)
    click_at(viewer, qtbot, ON_STEP)
    assert tool.preview is None  # the tool is off: a click selects traces, nothing is fitted
    tool.action.trigger()
    before = viewer.view.frame().astype(int)
    facet = fit_at(viewer, qtbot, ON_STEP)
    assert facet is tool.preview and facet.accepted
    assert np.linalg.norm(tool.point + viewer.session.project.origin - ON_STEP) < 0.02  # picked where clicked
    assert axial_angle(facet.normal, [1.0, 0.0, 0.0]) < 1e-4
    assert "dip 90.0°" in tool.message.text() and "planarity 1.00" in tool.message.text()
    assert tool.accept_button.isEnabled() and changed_pixels(viewer, before) > 200
    patch = actor_data(viewer.view.plotter.actors[PATCH_ACTOR])
    assert patch.GetNumberOfCells() == len(facet.faces)

    qtbot.mouseClick(tool.accept_button, Qt.MouseButton.LeftButton)
    (stored,) = viewer.session.project.facets()
    assert axial_angle(stored.normal, facet.normal) < 1e-9 and tool.list.count() == 1
    assert tool.list.item(0).text().startswith(f"{stored.id}: dip 90.0°")
    assert PATCH_ACTOR not in viewer.view.plotter.actors and not tool.accept_button.isEnabled()
    viewer.session.undo_stack.undo()
    assert viewer.session.project.facets() == [] and tool.list.count() == 0
    viewer.session.undo_stack.redo()
    assert [f.id for f in viewer.session.project.facets()] == [stored.id] and tool.list.count() == 1

    tool.list.setCurrentRow(0)
    qtbot.mouseClick(tool.remove_button, Qt.MouseButton.LeftButton)
    assert viewer.session.project.facets() == [] and tool.list.count() == 0
    viewer.session.undo_stack.undo()
    assert [f.id for f in viewer.session.project.facets()] == [stored.id]


def test_click_on_the_outcrop_face_is_rejected_with_the_reason(viewer, qtbot):
    tool = viewer.facet_tool
    tool.action.trigger()
    tool.radius.setValue(0.4)
    assert fit_at(viewer, qtbot, ON_WALL) is tool.preview and not tool.preview.accepted
    assert "rejected" in tool.message.text() and "outcrop face" in tool.message.text()
    assert not tool.accept_button.isEnabled()
    qtbot.mouseClick(tool.accept_button, Qt.MouseButton.LeftButton)
    assert viewer.session.project.facets() == []
    assert refit(viewer, qtbot, 0.25).n_points < 60  # a new radius refits around the same point
    assert "outcrop face" in tool.message.text()


def test_stored_facets_are_drawn_as_discs_when_the_project_opens(viewer, qtbot, tmp_path):
    tool = viewer.facet_tool
    tool.action.trigger()
    tool.radius.setValue(0.25)
    fit_at(viewer, qtbot, ON_STEP)
    tool.accept()
    assert "facets" in viewer.view.plotter.actors
    path = viewer.session.path
    viewer.session.close()
    assert tool.list.count() == 0
    viewer.session.open(path)
    qtbot.waitUntil(lambda: viewer.mesh is not None and "facets" in viewer.view.plotter.actors, timeout=20000)
    assert tool.list.count() == 1
    centre = np.array(actor_data(viewer.view.plotter.actors["facets"]).center)
    np.testing.assert_allclose(centre + viewer.session.project.origin, ON_STEP, atol=0.05)


def test_readout_and_radius_are_in_the_registered_frame(viewer, qtbot):
    register(viewer.session.project, 2.0, QUARTER_TURN)
    tool = viewer.facet_tool
    tool.action.trigger()
    tool.radius.setValue(0.5)  # metres of the registered frame: 0.25 m on the mesh
    facet = fit_at(viewer, qtbot, ON_STEP)
    assert facet is not None and facet.accepted
    mesh = viewer.mesh
    assert np.linalg.norm(mesh.face_centroids[facet.faces] - tool.point, axis=1).max() <= 0.25 + 1e-9
    # the east-facing step faces north once turned; its radius reads twice as long
    assert "dip 90.0° / dip direction 000.0°" in tool.message.text()
    assert f"radius {2 * facet.radius:.2f} m" in tool.message.text()


def test_a_click_on_a_large_mesh_returns_at_once_and_the_window_keeps_running(tmp_path, qtbot):
    """On 636k faces the face tree, the pick and the fit take about half a second of workers; the click
    returns in a few ms and the GUI thread keeps ticking. Wall-clock gaps between 10 ms ticks are held to the
    100 ms bound only when the machine is not overloaded by others (as in test_image_editor)."""
    window = step_viewer(tmp_path, qtbot, spacing=0.01)
    tool = window.facet_tool
    assert len(window.mesh.faces) > 600_000
    ticks = [(time.perf_counter(), time.thread_time())]
    timer = QTimer(interval=10)
    timer.timeout.connect(lambda: ticks.append((time.perf_counter(), time.thread_time())))
    timer.start()
    tool.action.trigger()  # sets off the face tree's build on a worker; the click comes before it is done
    with qtbot.waitSignal(tool.fitted, timeout=60_000) as fitted:
        start = time.perf_counter()
        click_at(window, qtbot, ON_STEP)
        clicked = time.perf_counter() - start
        assert not fitted.signal_triggered  # the fit is still to come: the click did not wait for it
    timer.stop()
    facet = fitted.args[0]
    assert facet is not None and facet.accepted and axial_angle(facet.normal, [1.0, 0.0, 0.0]) < 1e-4
    assert np.linalg.norm(tool.point + window.session.project.origin - ON_STEP) < 0.02
    assert clicked < 0.05, f"the click held the GUI thread {clicked * 1000:.0f} ms"
    assert_responsive(ticks)  # the timer ticked while the workers ran
    window.session.jobs.cancel_all(5000)
    window.session.close()
