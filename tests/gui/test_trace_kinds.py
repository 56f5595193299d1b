"""Trace kinds in the application: the kind new traces are drawn as, making selected traces a kind in
either window (one undoable edit over the 2D traces and the 3D traces made from them), the line patterns
and the colouring by kind, and a join refused across kinds."""

from __future__ import annotations

import sqlite3

import numpy as np
from PySide6.QtCore import Qt

from engine.render import KIND_COLORS
from engine.traces import Trace2D
from tests.gui.flows import actor_data, click
from tests.gui.test_viewer3d import click_trace, visible_trace
from tracemap_gui import commands
from tracemap_gui.image_editor import ImageEditor
from tracemap_gui.session import Session
from tracemap_gui.trace_layer import KIND_QCOLOURS, KIND_STYLES, PROPOSED


def stored_kinds(project_path, table):
    db = sqlite3.connect(f"file:{project_path}?mode=ro", uri=True)
    try:
        return dict(db.execute(f"SELECT id, kind FROM {table}"))
    finally:
        db.close()


def test_new_traces_are_drawn_as_the_kind_chosen_which_the_project_keeps(qtbot, editor, project_path):
    assert editor.kind_box.currentText() == "fracture"
    editor.kind_box.setCurrentText("bedding")
    assert editor.session.kind == "bedding"
    before = set(stored_kinds(project_path, "traces2d"))
    editor.set_tool("Draw polyline")
    for x, y in [(100, 100), (180, 140)]:
        click(qtbot, editor.view, x, y)
    qtbot.keyClick(editor.view, Qt.Key.Key_Return)
    (new,) = set(stored_kinds(project_path, "traces2d")) - before
    assert stored_kinds(project_path, "traces2d")[new] == "bedding"
    assert editor.traces.item._pens[new].style() == Qt.PenStyle.DashLine  # bedding is dashed in every colouring

    editor.session.close()
    again = Session()
    again.open(project_path)
    window = ImageEditor(again)
    qtbot.addWidget(window)
    assert window.kind_box.currentText() == "bedding" and again.kind == "bedding"
    again.close()


def test_make_selected_traces_a_kind_with_their_3d_traces_undoably(qtbot, editor, project_path):
    session = editor.session
    made = {p for t in session.traces3d() for p in t.parents}
    trace = next(t for t in session.traces2d(editor.view.image) if t.id in made)
    children = {t.id for t in session.traces3d() if trace.id in t.parents}
    editor.make_kind("vein")
    assert "select traces first" in editor.statusBar().currentMessage()
    session.select2d([trace.id])
    editor.make_kind("vein")
    kinds2d, kinds3d = stored_kinds(project_path, "traces2d"), stored_kinds(project_path, "traces3d")
    assert kinds2d[trace.id] == "vein" and {kinds3d[i] for i in children} == {"vein"}
    changed = {i for i, k in kinds2d.items() if k == "vein"}
    assert session.undo_stack.undoText() == f"Make {len(changed) + len(children)} traces vein"
    assert {t.kind for t in session.traces3d() if t.id in children} == {"vein"}  # the session's cache follows
    session.select2d([])
    assert editor.traces.item._pens[trace.id].style() == KIND_STYLES["vein"] == Qt.PenStyle.DotLine
    editor.kind_colour_action.trigger()
    assert editor.traces.colour_by == "kind" and session.setting("editor.colour_by") == "kind"
    assert editor.traces.item._pens[trace.id].color() == KIND_QCOLOURS["vein"]
    others = [t for t in session.traces2d(editor.view.image) if t.kind == "fracture"]
    assert editor.traces.item._pens[others[0].id].color() == KIND_QCOLOURS["fracture"]

    session.undo_stack.undo()
    assert set(stored_kinds(project_path, "traces2d").values()) == {"fracture"}
    assert set(stored_kinds(project_path, "traces3d").values()) == {"fracture"}
    assert editor.traces.item._pens[trace.id].style() == Qt.PenStyle.SolidLine
    session.undo_stack.redo()
    assert stored_kinds(project_path, "traces3d")[min(children)] == "vein"
    session.select2d([trace.id])
    editor.make_kind("vein")
    assert "already" in editor.statusBar().currentMessage() and session.undo_stack.count() == 1


def test_traces_of_two_kinds_are_not_joined(qtbot, editor, project_path):
    session = editor.session
    a = Trace2D(0, "photo_01", np.array([[100.0, 300.0], [200.0, 300.0]]), kind="bedding")
    b = Trace2D(0, "photo_01", np.array([[210.0, 300.0], [300.0, 300.0]]))
    session.push(commands.AddTraces2D(session, [a, b]))
    before = stored_kinds(project_path, "traces2d")
    editor.set_tool("Join")
    click(qtbot, editor.view, 150, 300)
    click(qtbot, editor.view, 250, 300)
    assert stored_kinds(project_path, "traces2d") == before
    assert editor.hint.text().startswith("Not joined: one trace is bedding, the other fracture")


def test_the_3d_viewer_makes_selected_traces_a_kind_and_colours_by_kind(viewer, qtbot, project_path):
    trace = visible_trace(viewer)
    click_trace(viewer, qtbot, trace)
    assert viewer.session.selected3d == {trace.id}
    assert "kind" in viewer.info.toPlainText() and "bedding" not in viewer.info.toPlainText()
    viewer.make_kind("bedding")
    assert stored_kinds(project_path, "traces3d")[trace.id] == "bedding"
    kinds2d = stored_kinds(project_path, "traces2d")
    assert {kinds2d[p] for p in trace.parents} == {"bedding"}
    assert "bedding" in viewer.info.toPlainText()  # the readout follows the edit
    viewer.color_box.setCurrentText("kind")
    assert viewer.style.color_by == "kind"
    viewer.session.select3d([])
    assert drawn_colour(viewer, trace.id) == KIND_COLORS["bedding"]
    assert drawn_colour(viewer, next(t.id for t in viewer.session.traces3d() if t.kind == "fracture")) \
        == KIND_COLORS["fracture"]
    viewer.session.undo_stack.undo()
    assert stored_kinds(project_path, "traces3d")[trace.id] == "fracture"
    assert drawn_colour(viewer, trace.id) == KIND_COLORS["fracture"]


def drawn_colour(viewer, trace_id):
    """The colour the 3D view draws a trace in (its cells in the traces actor)."""
    lines = actor_data(viewer.view.plotter.actors["traces"])
    (colour,) = {tuple(int(c) for c in rgb) for rgb in lines.cell_data["rgb"][lines.cell_data["trace_id"] == trace_id]}
    return colour


def test_autotrace_proposes_the_kind_the_other_photos_trace(qtbot, editor):
    """With the other photos' traces bedding, the photo's proposals along them are bedding, as
    `engine.delineate.kinds_traced_elsewhere` gives them, and Accept stores them so."""
    from dataclasses import replace

    from engine.delineate import kinds_traced_elsewhere
    from engine.raytrace import RayTracer

    session, project = editor.session, editor.session.project
    others = [replace(t, kind="bedding") for t in project.traces2d() if t.image != "photo_01"]
    project.update_traces2d(others)
    session.reload()
    session.push(commands.RemoveTraces2D(session, session.traces2d("photo_01")))
    panel = editor.autotrace
    with qtbot.waitSignal(editor.proposals.changed, timeout=60_000):
        panel.run_button.click()
    qtbot.waitUntil(lambda: not session.jobs.running, timeout=10_000)
    proposals = list(editor.proposals.traces)
    mesh = project.load_mesh()
    expected = kinds_traced_elsewhere([replace(t, kind="fracture") for t in proposals], "photo_01", others,
                                      session.cameras(), RayTracer(mesh.vertices, mesh.faces))
    assert [t.kind for t in proposals] == [t.kind for t in expected]
    n = sum(t.kind == "bedding" for t in proposals)
    assert 0 < n < len(proposals)
    colours = {t.kind: editor.proposals.item._pens[k].color() for k, t in enumerate(proposals)}
    assert colours == {"bedding": KIND_QCOLOURS["bedding"], "fracture": PROPOSED}  # told apart before Accept
    panel.accept_button.click()
    assert sum(t.kind == "bedding" for t in project.traces2d(["photo_01"])) == n
