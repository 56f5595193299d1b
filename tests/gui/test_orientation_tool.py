"""The orientation disc, the candidate ring and manual orientation in the offscreen 3D viewer (quick demo)."""

import re

import numpy as np
import pytest
from PySide6.QtCore import QPoint, Qt
from PySide6.QtWidgets import QDialogButtonBox

from engine.errors import InputError
from engine.orientation import axial_angle, dip_dipdir_to_normal, normal_to_dip_dipdir
from engine.traces import Trace3D
from tests.gui.flows import QUARTER_TURN, actor_data, register
from tests.gui.test_viewer3d import click_trace, display_position, visible_trace
from tracemap_gui.commands import ReplaceTraces3D
from tracemap_gui.orientation_tool import ACTORS, RING_SCALE, parse_dip_dipdir
from tracemap_gui.scene_view import display_coordinates


def actor_points(window, name):
    return np.asarray(actor_data(window.view.plotter.actors[name]).points)


def current(window, trace_id):
    return next(t for t in window.session.traces3d() if t.id == trace_id)


def curve_centroid(points):
    """Centroid of the polyline as a curve (segment midpoints weighted by length): the resampled mean's oracle."""
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return ((points[:-1] + points[1:]) / 2 * lengths[:, None]).sum(axis=0) / lengths.sum()


def click_display(window, qtbot, x, y):
    canvas = window.view._canvas
    qtbot.mouseClick(canvas, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                     QPoint(x, canvas.height() - 1 - y))


def visible_probabilistic(window):
    """A long trace oriented by the probabilistic solver whose midpoint picks back to itself."""
    w, h = window.view.plotter.window_size
    for trace in sorted(window.session.traces3d(), key=lambda t: -t.surface_length):
        x, y = display_position(window, trace.points[len(trace.points) // 2])
        if trace.method == "probabilistic" and 20 < x < w - 20 and 20 < y < h - 20 \
                and window.pick_trace(x, y) == trace.id:
            return trace
    pytest.fail("no pickable probabilistic trace in view")


def selected(viewer, qtbot, find=visible_trace):
    trace = find(viewer)
    click_trace(viewer, qtbot, trace)
    assert viewer.session.selected3d == {trace.id}
    return trace


def test_disc_and_ring_geometry(viewer, qtbot):
    trace = selected(viewer, qtbot)
    c = curve_centroid(trace.points)
    axis = (trace.points[-1] - trace.points[0]) / trace.chord_length
    ring = actor_points(viewer, "orientation-ring")
    assert len(ring) == 360
    centre = ring.mean(axis=0)
    assert np.linalg.norm(centre - c) < 0.02 * trace.chord_length
    r = np.linalg.norm(ring - centre, axis=1)
    np.testing.assert_allclose(r, RING_SCALE * trace.chord_length / 2, rtol=1e-5)
    assert np.abs((ring - centre) @ axis).max() < 1e-5 * r.max()  # the ring lies in the plane ⟂ the end-node axis
    disc = actor_points(viewer, "orientation-disc")
    assert np.abs((disc - centre) @ trace.normal).max() < 1e-5 * r.max()  # in the trace's current plane
    assert np.linalg.norm(disc - centre, axis=1).max() == pytest.approx(trace.chord_length / 2, rel=1e-5)
    marks = actor_points(viewer, "orientation-current")  # the current pole's place on the ring, both antipodes
    on_circle = trace.normal - (trace.normal @ axis) * axis
    on_circle /= np.linalg.norm(on_circle)
    np.testing.assert_allclose(np.abs((marks - centre) @ on_circle), r[0], rtol=1e-5)
    assert len(actor_points(viewer, "orientation-solutions")) == 2  # an eigen trace: only its eigen pole


def test_marks_of_a_probabilistic_trace(viewer, qtbot):
    trace = selected(viewer, qtbot, visible_probabilistic)
    glyph = viewer.orientation_tool.glyph
    marks = (actor_points(viewer, "orientation-solutions") - glyph.centroid) / glyph.ring_radius
    eigen = np.asarray(trace.extra["eigen_normal"])
    axis = (trace.points[-1] - trace.points[0]) / trace.chord_length
    eigen_on_circle = eigen - (eigen @ axis) * axis
    expected = [eigen_on_circle / np.linalg.norm(eigen_on_circle), trace.normal]  # eigen and solver, both ends
    assert len(marks) == 4
    for pole in expected:
        assert min(axial_angle(m, pole) for m in marks) < 0.01


def test_glyph_follows_the_selection(viewer, qtbot):
    trace = selected(viewer, qtbot)
    other = next(t for t in viewer.session.traces3d() if t.id != trace.id and len(t.points) >= 3)
    viewer.session.select3d({trace.id, other.id})
    assert not set(ACTORS) & set(viewer.view.plotter.actors)
    viewer.session.select3d({other.id})
    assert actor_points(viewer, "orientation-ring").mean(axis=0) == pytest.approx(curve_centroid(other.points),
                                                                                 abs=0.02 * other.chord_length)
    stub = Trace3D(0, other.points[:2], other.uv[:2], other.face[:2], other.image_index[:2], other.images)
    add = ReplaceTraces3D(viewer.session, [], [stub], "Add a 2-vertex trace")
    viewer.session.push(add)
    viewer.session.select3d({add.added[0].id})
    assert not set(ACTORS) & set(viewer.view.plotter.actors)
    assert "no candidate circle" in viewer.statusBar().currentMessage()
    viewer.session.select3d(())
    assert not set(ACTORS) & set(viewer.view.plotter.actors)


def test_display_coordinates_match_vtk(viewer, qtbot):
    trace = selected(viewer, qtbot)
    ours = display_coordinates(viewer.view.plotter.renderer, trace.points[::10])
    theirs = np.array([display_position(viewer, p) for p in trace.points[::10]])
    assert np.abs(ours - theirs).max() <= 0.51  # display_position rounds to whole pixels


def test_click_on_ring_sets_orientation_undoably(viewer, qtbot, project_path):
    trace = selected(viewer, qtbot, visible_probabilistic)  # its solver's fields must come back on undo
    assert "mode" in trace.extra
    before = viewer.session.project.traces3d()
    tool = viewer.orientation_tool
    assert tool.action.shortcut().toString() == "O"
    tool.action.trigger()
    glyph = tool.glyph
    phi0 = glyph.angle_of(trace.normal)
    w, h = viewer.view.plotter.window_size
    for phi in phi0 + np.radians([30.0, 210.0, -30.0, 150.0]):  # the ring point 30° from the current pole
        x, y = display_position(viewer, glyph.centroid + glyph.ring_radius * glyph.pole_at(phi))
        if 10 < x < w - 10 and 10 < y < h - 10:
            break
    else:
        pytest.fail("no ring point 30° from the pole is in view")
    wanted = glyph.pole_at(phi)
    click_display(viewer, qtbot, x, y)

    edited = current(viewer, trace.id)
    assert axial_angle(edited.normal, wanted) < 1.0
    assert axial_angle(edited.normal, glyph.pole_at(phi0)) == pytest.approx(30.0, abs=1.0)
    assert edited.method == "manual" and viewer.session.selected3d == {trace.id}  # the click selected nothing
    stored = next(t for t in viewer.session.project.traces3d() if t.id == trace.id)
    assert stored.method == "manual" and axial_angle(stored.normal, wanted) < 1.0
    dip, dipdir = normal_to_dip_dipdir(edited.normal)
    info = viewer.info.toPlainText()
    assert "manual" in info and f"{float(dip):.1f}° / {float(dipdir):05.1f}°" in info
    # the disc turned with the plane
    disc = actor_points(viewer, "orientation-disc")
    assert np.abs((disc - disc.mean(axis=0)) @ edited.normal).max() < 1e-5 * trace.chord_length

    viewer.session.undo_stack.undo()
    original = next(t for t in before if t.id == trace.id)
    for restored in (current(viewer, trace.id), next(t for t in viewer.session.project.traces3d() if t.id == trace.id)):
        np.testing.assert_array_equal(restored.normal, original.normal)
        assert (restored.method, restored.K, restored.M) == (original.method, original.K, original.M)
        assert restored.extra == original.extra
    viewer.session.undo_stack.redo()
    assert current(viewer, trace.id).method == "manual"
    assert axial_angle(current(viewer, trace.id).normal, wanted) < 1.0

    viewer.session.close()
    viewer.session.open(project_path)
    reopened = current(viewer, trace.id)
    assert reopened.method == "manual" and axial_angle(reopened.normal, wanted) < 1.0
    qtbot.waitUntil(lambda: viewer.mesh is not None, timeout=60_000)  # the machine may be busy


def test_click_off_the_ring_selects_as_usual(viewer, qtbot):
    trace = selected(viewer, qtbot)
    viewer.orientation_tool.action.trigger()
    click_display(viewer, qtbot, 2, 2)  # a corner, far from the ring
    assert viewer.session.selected3d == frozenset()
    assert current(viewer, trace.id).method == trace.method and viewer.session.undo_stack.count() == 0


def test_typed_dip_and_dip_direction(viewer, qtbot):
    trace = selected(viewer, qtbot)
    tool = viewer.orientation_tool
    wanted = tool.glyph.pole_at(tool.glyph.angle_of(trace.normal) + np.radians(40.0))
    dip, dipdir = (float(v) for v in normal_to_dip_dipdir(wanted))

    def type_in(dip_text, dipdir_text):
        tool.type_action.trigger()
        dialog = tool.dialog
        dialog.dip.setText(dip_text)
        dialog.dipdir.setText(dipdir_text)
        qtbot.mouseClick(dialog.buttons.button(QDialogButtonBox.StandardButton.Ok), Qt.MouseButton.LeftButton)
        return dialog

    dialog = type_in("95", f"{dipdir}")
    assert dialog.isVisible() and dialog.message.text() == "dip 95: expected 0 to 90 degrees"
    dialog.dip.setText(f"{dip}")
    dialog.dipdir.setText("north")
    qtbot.mouseClick(dialog.buttons.button(QDialogButtonBox.StandardButton.Ok), Qt.MouseButton.LeftButton)
    assert dialog.isVisible() and "dip direction 'north': expected a number of degrees" in dialog.message.text()
    assert viewer.session.undo_stack.count() == 0 and current(viewer, trace.id).method == trace.method
    dialog.reject()

    dialog = type_in(f"{dip:.4f}", f"{dipdir:.4f}")
    assert not dialog.isVisible()
    edited = current(viewer, trace.id)
    assert edited.method == "manual" and axial_angle(edited.normal, wanted) < 0.01

    # a plane not containing the end-node axis: its nearest candidate is stored, and the user is told
    axis = tool.glyph.axis
    off = dip_dipdir_to_normal(*normal_to_dip_dipdir(wanted + 0.5 * axis))
    type_in(*(f"{float(v):.3f}" for v in normal_to_dip_dipdir(off)))
    moved = current(viewer, trace.id)
    assert abs(moved.normal @ axis) < 1e-9
    assert "does not contain the end-node axis" in viewer.statusBar().currentMessage()
    viewer.session.undo_stack.undo()
    viewer.session.undo_stack.undo()
    np.testing.assert_array_equal(current(viewer, trace.id).normal, trace.normal)


def test_readouts_and_typed_orientation_are_in_the_registered_frame(viewer, qtbot):
    turn = QUARTER_TURN
    register(viewer.session.project, 2.0, turn)
    trace = selected(viewer, qtbot)
    viewer._show_info()
    dip, dipdir = (float(v) for v in normal_to_dip_dipdir(turn @ trace.normal))
    shown = viewer.info.toPlainText()
    assert f"{dip:.1f}° / {dipdir:05.1f}°" in shown and f"{2 * trace.surface_length:.3f} m" in shown
    assert "registered" in shown
    tool = viewer.orientation_tool
    wanted = tool.glyph.pole_at(tool.glyph.angle_of(trace.normal) + np.radians(40.0))  # in the mesh frame
    tool.type_action.trigger()
    dialog = tool.dialog
    assert float(dialog.dipdir.text()) == pytest.approx(dipdir, abs=0.06)  # it opens with the shown values
    typed = [float(v) for v in normal_to_dip_dipdir(turn @ wanted)]  # as the registered frame reads
    dialog.dip.setText(f"{typed[0]:.4f}")
    dialog.dipdir.setText(f"{typed[1]:.4f}")
    qtbot.mouseClick(dialog.buttons.button(QDialogButtonBox.StandardButton.Ok), Qt.MouseButton.LeftButton)
    assert axial_angle(current(viewer, trace.id).normal, wanted) < 0.01  # stored in the mesh frame


@pytest.mark.parametrize("dip, dipdir, message", [
    ("-1", "10", "dip -1: expected 0 to 90 degrees"),
    ("10", "360.5", "dip direction 360.5: expected 0 to 360 degrees"),
    ("", "10", "dip '': expected a number of degrees"),
])
def test_parse_refuses_out_of_range(dip, dipdir, message):
    with pytest.raises(InputError, match=re.escape(message)):
        parse_dip_dipdir(dip, dipdir)


def test_parse_accepts_degree_signs_and_north_as_360():
    assert parse_dip_dipdir(" 45° ", "360") == (45.0, 0.0)
