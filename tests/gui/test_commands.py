"""Undoable commands against a real project: each redo and undo is stored at once, ids survive undo/redo."""

from __future__ import annotations

import numpy as np
import pytest

from engine.errors import TracemapError
from engine.traces import Trace2D
from tests.gui.flows import stored_traces2d, stored_traces3d_parents
from tracemap_gui import commands, polyline_edit

LINE = np.array([[100.0, 100.0], [200.0, 150.0], [300.0, 120.0]])


def test_add_undo_redo_keeps_the_id_and_is_stored_at_once(session, project_path, qtbot):
    before = stored_traces2d(project_path)
    with qtbot.waitSignal(session.traces2d_changed) as changed:
        session.push(commands.AddTraces2D(session, [Trace2D(0, "photo_01", LINE)]))
    assert changed.args == ["photo_01"]
    (new_id,) = set(stored_traces2d(project_path)) - set(before)
    assert np.array_equal(stored_traces2d(project_path)[new_id][1], LINE)
    assert new_id in {t.id for t in session.traces2d("photo_01")}

    session.undo_stack.undo()
    assert stored_traces2d(project_path).keys() == before.keys()
    session.undo_stack.redo()
    assert new_id in stored_traces2d(project_path)  # the same id, so later commands naming it still work


def test_editor_commands_keep_the_stored_2d_components_through_undo(session):
    def components():
        return {t.id: t.component for t in session.project.traces2d(["photo_01"])}

    before = components()
    assert len(set(before.values())) > 1  # the demo's traces are labelled on import: several groups
    across = Trace2D(0, "photo_01", np.array([[0.0, 0.0], [639.0, 479.0], [0.0, 479.0], [639.0, 0.0]]))
    session.push(commands.AddTraces2D(session, [across]))  # would join groups if the project relabelled
    after = components()
    assert {i: after[i] for i in before} == before and len(after) == len(before) + 1
    session.undo_stack.undo()
    assert components() == before


def test_split_join_edit_and_their_undo(session, project_path):
    original = stored_traces2d(project_path)
    trace = session.traces2d("photo_01")[0]
    session.push(commands.SplitTrace2D(session, trace, 0, 0.5))
    pieces = [t for t in session.traces2d("photo_01") if t.id not in original]
    assert len(pieces) == 2 and trace.id not in {t.id for t in session.traces2d("photo_01")}
    assert np.array_equal(pieces[0].polyline[-1], pieces[1].polyline[0])
    session.push(commands.JoinTraces2D(session, *pieces))
    (joined,) = [t for t in session.traces2d("photo_01") if t.id not in original]
    assert np.allclose(joined.polyline, polyline_edit.insert_vertex(trace.polyline, 0, 0.5))  # + the cut
    session.push(commands.EditTrace2D(session, joined, joined.polyline + 1.0))
    assert np.allclose(stored_traces2d(project_path)[joined.id][1], joined.polyline + 1.0)
    assert stored_traces2d(project_path)[joined.id][2] == "manual"
    for _ in range(3):
        session.undo_stack.undo()
    now = stored_traces2d(project_path)
    assert now.keys() == original.keys()
    assert np.array_equal(now[trace.id][1], original[trace.id][1])


def test_removing_2d_traces_removes_their_3d_traces_until_undone(session, project_path):
    parents = {p for t in session.traces3d() for p in t.parents}
    trace = next(t for t in session.traces2d("photo_01") if t.id in parents)
    children = {t.id for t in session.traces3d() if trace.id in t.parents}
    session.push(commands.SplitTrace2D(session, trace, len(trace.polyline) // 2, 0.5))
    assert not children & set(stored_traces3d_parents(project_path))  # re-extracting will not duplicate them
    assert not children & {t.id for t in session.traces3d()}
    session.undo_stack.undo()
    assert children <= set(stored_traces3d_parents(project_path)) and children <= {t.id for t in session.traces3d()}


def test_accepting_proposals_replaces_the_earlier_automatic_traces_only(session, project_path):
    manual = {t.id for t in session.traces2d("photo_02")}
    session.push(commands.ReplaceAutoTraces(session, "photo_02", [Trace2D(0, "", LINE), Trace2D(0, "", LINE + 5)]))
    session.push(commands.ReplaceAutoTraces(session, "photo_02", [Trace2D(0, "", LINE + 10)]))
    traces = session.traces2d("photo_02")
    assert {t.id for t in traces if t.source == "manual"} == manual
    (auto,) = [t for t in traces if t.source == "auto"]
    assert np.array_equal(auto.polyline, LINE + 10)
    session.undo_stack.undo()
    assert len([t for t in session.traces2d("photo_02") if t.source == "auto"]) == 2


def test_3d_commands_for_the_viewer(session, project_path, qtbot):
    first, second = session.traces3d()[:2]
    with qtbot.waitSignal(session.traces3d_changed):
        session.push(commands.EditTraces3D.setting(session, [first, second], "Set 2", set_id=2, term_end="T"))
    assert {t.set_id for t in session.traces3d()[:2]} == {2}
    merged = commands.ReplaceTraces3D(session, [first, second], [first], "Merge")
    session.push(merged)
    ids = {t.id for t in session.traces3d()}
    assert second.id not in ids and first.id not in ids and merged.added[0].id in ids
    session.undo_stack.undo()
    session.undo_stack.undo()
    restored = {t.id: t for t in session.traces3d()}
    assert restored[first.id].set_id == first.set_id and restored[second.id].term_end == second.term_end
    assert set(stored_traces3d_parents(project_path)) == set(restored)


def test_a_failing_edit_changes_nothing_and_is_not_pushed(session, project_path):
    before = stored_traces2d(project_path)
    bad = commands.AddTraces2D(session, [Trace2D(0, "photo_01", LINE), Trace2D(0, "no such photo", LINE)])
    with pytest.raises(Exception):  # the foreign key of the second trace fails: the whole edit rolls back
        session.push(bad)
    assert stored_traces2d(project_path).keys() == before.keys()
    assert session.undo_stack.count() == 0


def test_a_failing_undo_is_reported_not_raised(session, qtbot):
    trace = session.traces2d("photo_01")[0]
    session.push(commands.RemoveTraces2D(session, [trace]))
    session.project.add_traces2d([Trace2D(0, "photo_01", LINE)])
    with session.project.transaction() as db:  # someone else took the id back meanwhile
        db.execute("UPDATE traces2d SET id = ? WHERE id = (SELECT max(id) FROM traces2d)", (trace.id,))
    with qtbot.waitSignal(session.failed) as failed:
        session.undo_stack.undo()
    assert failed.args[0].startswith("Erase traces: ")


def test_removing_selected_traces_deselects_them(session):
    a, b = session.traces2d("photo_01")[:2]
    session.select2d([a.id, b.id])
    session.push(commands.RemoveTraces2D(session, [a]))
    assert session.selected2d == {b.id}


def test_split_at_an_end_is_refused_with_a_message(session):
    trace = session.traces2d("photo_01")[0]
    with pytest.raises(TracemapError, match="end"):
        commands.SplitTrace2D(session, trace, 0, 0.0)


def test_trim_clears_the_orientation_and_relabels_components(session, project_path):
    """A trace cut to its first vertices loses its pole (fitted to the whole trace) and, where the part cut off
    was its contact with others, its component; undo restores both."""
    from engine.merge import relabel_components, trim

    tolerance = 0.05
    traces = session.traces3d()
    before = {t.id: t.component for t in traces}
    for trace in traces:  # one whose trimming splits a component, so the relabelling shows
        cut = trim(trace, 0, 3)
        expected = {t.id: t.component for t in relabel_components(
            [*(t for t in traces if t.id != trace.id), cut], tolerance)}
        if len(set(expected.values())) > len(set(before.values())):
            break
    else:
        pytest.fail("no trace of the demo splits a component when trimmed")
    assert trace.normal is not None
    session.push(commands.TrimTrace3D(session, trace, cut, tolerance))
    stored = {t.id: t for t in session.traces3d()}
    assert {i: t.component for i, t in stored.items()} == expected
    assert stored[trace.id].normal is None and stored[trace.id].method == "" and len(stored[trace.id].points) == 3
    assert "eigen_normal" not in stored[trace.id].extra
    session.undo_stack.undo()
    restored = {t.id: t for t in session.traces3d()}
    assert {i: t.component for i, t in restored.items()} == before
    np.testing.assert_allclose(restored[trace.id].normal, trace.normal)
