"""The 3D viewer's merge, merge-suggestion and trim tools, driven by real clicks and keys in the offscreen viewer.

The quick demo project has its duplicates merged already, so the fixture ray-traces its 2D traces again
without merging: each fracture seen in two photos then has two 3D traces, the real pairs to merge.
"""

import shutil
from dataclasses import replace

import numpy as np
import pytest
from PySide6.QtCore import QPoint, Qt
from PySide6.QtWidgets import QMessageBox

from engine.extract import extract_traces
from engine.merge import MergeSuggestion, Overlap, merge_pair, relabel_components, suggest_merges, trim
from engine.project import Project
from engine.raytrace import RayTracer
from engine.sight import Sight
from tests.gui.flows import open_viewer, register
from tests.gui.test_viewer3d import display_position
from tracemap_gui.commands import ReplaceTraces3D
from tracemap_gui.merge_tool import DIM_COLOR, PREVIEW_ACTOR, PREVIEW_COLOR, Suggested
from tracemap_gui.session import Session

TOLERANCE = 0.03  # the tool's default


@pytest.fixture(scope="module")
def unmerged_demo(quick_demo, tmp_path_factory):
    folder = tmp_path_factory.mktemp("unmerged")
    shutil.copytree(quick_demo / "data", folder / "data")
    shutil.copy2(quick_demo / "demo.tracemap", folder / "demo.tracemap")
    with Project.open(folder / "demo.tracemap") as project:
        mesh = project.load_mesh()
        result = extract_traces(project.traces2d(), project.cameras(), RayTracer(mesh.vertices, mesh.faces))
        with project.transaction() as db:
            project.remove_traces3d([t.id for t in project.traces3d()], db)
            project.add_traces3d(result.traces, db)
    return folder


@pytest.fixture
def viewer(unmerged_demo, tmp_path, qtbot):
    shutil.copytree(unmerged_demo / "data", tmp_path / "data")
    shutil.copy2(unmerged_demo / "demo.tracemap", tmp_path / "demo.tracemap")
    session = Session()
    session.open(tmp_path / "demo.tracemap")
    window = open_viewer(qtbot, session)
    window.activateWindow()
    qtbot.waitUntil(window.isActiveWindow)  # shortcuts only reach the active window
    yield window
    session.jobs.cancel_all(5000)
    session.close()


def click_at(window, qtbot, x, y, modifier=Qt.KeyboardModifier.NoModifier):
    canvas = window.view._canvas
    qtbot.mouseClick(canvas, Qt.MouseButton.LeftButton, modifier, QPoint(x, canvas.height() - 1 - y))


def key(window, qtbot, k):
    qtbot.keyClick(window.view._canvas, k)


def pickable_vertex(window, trace):
    """Display position of a vertex of `trace` inside the view that picks back to the trace, or None (a
    duplicate drawn over it hides much of it)."""
    w, h = window.view.plotter.window_size
    middle = len(trace.points) // 2
    for k in sorted(range(0, len(trace.points), 3), key=lambda k: abs(k - middle)):
        x, y = display_position(window, trace.points[k])
        if 20 < x < w - 20 and 20 < y < h - 20 and window.pick_trace(x, y) == trace.id:
            return x, y
    return None


def longest_clickable(window):
    return next(t for t in sorted(window.session.traces3d(), key=lambda t: -len(t.points))
                if pickable_vertex(window, t))


def clickable_pair(window):
    """A real duplicate pair (suggest_merges) and a position on each where a click selects it."""
    by_id = {t.id: t for t in window.session.traces3d()}
    for s in suggest_merges(list(by_id.values()), tolerance=TOLERANCE):
        a, b = by_id[s.a_id], by_id[s.b_id]
        pa, pb = pickable_vertex(window, a), pickable_vertex(window, b)
        if pa and pb:
            return a, b, pa, pb
    pytest.fail("no duplicate pair with both traces clickable")


def select_pair(window, qtbot):
    a, b, pa, pb = clickable_pair(window)
    click_at(window, qtbot, *pa)
    click_at(window, qtbot, *pb, Qt.KeyboardModifier.ShiftModifier)
    assert window.session.selected3d == {a.id, b.id}
    return a, b


def preview_points(window):
    actor = window.view.plotter.actors.get(PREVIEW_ACTOR)
    return None if actor is None else np.asarray(actor.mapper.dataset.points)


def colour_share(window, colour):
    frame = window.view.frame().astype(int)
    return np.mean(np.abs(frame - np.array(colour)).max(axis=2) <= 10)


def trace_colours(window, ids):
    data = window.view.plotter.actors["traces"].mapper.dataset
    mask = np.isin(np.asarray(data.cell_data["trace_id"]), list(ids))
    return np.asarray(data.cell_data["rgb"])[mask]


def by_id(traces):
    return {t.id: t for t in traces}


def test_merge_preview_accept_undo_redo_and_reopen(viewer, qtbot):
    session, tool = viewer.session, viewer.merge_tool
    before = by_id(session.traces3d())
    a, b = select_pair(viewer, qtbot)
    expected = merge_pair(a, b, tolerance=TOLERANCE)
    assert colour_share(viewer, PREVIEW_COLOR) == 0
    key(viewer, qtbot, Qt.Key.Key_M)
    np.testing.assert_allclose(preview_points(viewer), expected.points, atol=1e-9)
    assert colour_share(viewer, PREVIEW_COLOR) > 1e-4  # the preview is drawn
    assert (trace_colours(viewer, {a.id, b.id}) == DIM_COLOR).all()  # its sources dimmed
    assert tool.dock.isVisible() and len(session.project.traces3d()) == len(before)  # nothing stored yet

    key(viewer, qtbot, Qt.Key.Key_Return)
    stored = by_id(session.project.traces3d())  # on disk
    assert a.id not in stored and b.id not in stored and len(stored) == len(before) - 1
    (new_id,) = set(stored) - set(before)
    np.testing.assert_allclose(stored[new_id].points, expected.points, atol=1e-9)
    assert sorted(stored[new_id].extra["merged_from"]) == sorted([a.id, b.id])
    rest = [t for i, t in before.items() if i not in (a.id, b.id)]
    labels = [t.component for t in relabel_components([*rest, expected], TOLERANCE)]
    assert [stored[t.id].component for t in rest] + [stored[new_id].component] == labels
    assert preview_points(viewer) is None and not tool.dock.isVisible() and session.selected3d == {new_id}

    session.undo_stack.undo()
    restored = by_id(session.project.traces3d())
    assert set(restored) == set(before)
    for i, t in before.items():
        np.testing.assert_array_equal(restored[i].points, t.points)
        assert restored[i].component == t.component
    session.undo_stack.redo()
    assert new_id in by_id(session.project.traces3d()) and a.id not in by_id(session.traces3d())

    path = session.path
    session.close()
    with Project.open(path) as project:
        again = by_id(project.traces3d())
    np.testing.assert_allclose(again[new_id].points, expected.points, atol=1e-9)
    assert a.id not in again and b.id not in again


def test_cancel_stores_nothing_and_restores_colours(viewer, qtbot):
    session = viewer.session
    a, b = select_pair(viewer, qtbot)
    colours = trace_colours(viewer, {a.id, b.id}).copy()
    key(viewer, qtbot, Qt.Key.Key_M)
    assert preview_points(viewer) is not None
    key(viewer, qtbot, Qt.Key.Key_Escape)
    assert preview_points(viewer) is None and viewer.merge_tool.mode is None
    np.testing.assert_array_equal(trace_colours(viewer, {a.id, b.id}), colours)
    assert {a.id, b.id} <= set(by_id(session.project.traces3d())) and session.undo_stack.count() == 0


def test_merge_error_is_shown_and_nothing_changes(viewer, qtbot):
    session = viewer.session
    other = next(t for t in session.traces3d() if len(t.points) > 10)
    command = ReplaceTraces3D(session, [], [trim(other, 0, 2)], "add a 2-vertex trace")
    session.push(command)
    session.select3d({command.added[0].id, other.id})
    n = len(session.project.traces3d())
    viewer.merge_tool.merge_action.trigger()
    box = viewer.findChild(QMessageBox, "error-dialog")
    assert box is not None and "at least 3" in box.informativeText()
    assert viewer.merge_tool.mode is None and preview_points(viewer) is None
    assert len(session.project.traces3d()) == n and session.undo_stack.count() == 1  # only the set-up edit
    box.close()


def test_suggestions_step_frame_accept_and_resolve_chains(viewer, qtbot):
    session, tool = viewer.session, viewer.merge_tool
    traces = by_id(session.traces3d())
    mesh = viewer.mesh
    sight = Sight(mesh, session.cameras(), RayTracer(mesh.vertices, mesh.faces))
    expected = suggest_merges(list(traces.values()), tolerance=TOLERANCE, sight=sight, review=True)
    assert any("no photo shows" in s.reason for s in expected)  # the tool passes the survey
    tool.suggest_action.trigger()
    qtbot.waitUntil(lambda: tool.mode == "suggest", timeout=20000)
    assert [(s.suggestion.a_id, s.suggestion.b_id) for s in tool.suggestions] == [(s.a_id, s.b_id) for s in expected]
    assert tool.panel.list.count() == len(expected)

    key(viewer, qtbot, Qt.Key.Key_N)
    assert tool.index == 1 and tool.panel.list.currentRow() == 1
    key(viewer, qtbot, Qt.Key.Key_B)
    assert tool.index == 0
    first = expected[0]
    np.testing.assert_allclose(preview_points(viewer),
                               merge_pair(traces[first.a_id], traces[first.b_id], tolerance=TOLERANCE,
                                          sight=sight).points,
                               atol=1e-9)
    centre = np.vstack([traces[first.a_id].points, traces[first.b_id].points]).mean(axis=0)
    x, y = display_position(viewer, centre)
    w, h = viewer.view.plotter.window_size
    assert abs(x - w / 2) < w / 4 and abs(y - h / 2) < h / 4  # the view is framed on the pair

    # accept a suggestion that has a chain partner, then visit the partner: it names the merged trace
    k, partner = next((k, j) for k, s in enumerate(expected) for j, t in enumerate(expected)
                      if j > k and {s.a_id, s.b_id} & {t.a_id, t.b_id})
    tool.panel.list.setCurrentRow(k)
    key(viewer, qtbot, Qt.Key.Key_Return)
    assert tool.suggestions[k].status == "accepted"
    stored = by_id(session.project.traces3d())
    new_id = max(stored)
    assert tool.panel.list.item(k).text().startswith("✓")
    tool.go_to(partner)
    accepted, later = expected[k], expected[partner]
    (other,) = {later.a_id, later.b_id} - {accepted.a_id, accepted.b_id}
    if suggest_merges([stored[new_id], stored[other]], tolerance=TOLERANCE, sight=sight):  # still one: merge it
        assert {t.id for t in tool.proposal.sources} == {new_id, other}
    else:
        assert tool.proposal is None and "do not look like one fracture" in tool.panel.message.text()

    tool.skip_action.trigger()
    assert tool.suggestions[partner].status == "skipped" and tool.index != partner


def test_accept_all_remaining_resolves_chains_in_one_undo_step(viewer, qtbot):
    session, tool = viewer.session, viewer.merge_tool
    traces = by_id(session.traces3d())
    found = suggest_merges(list(traces.values()), tolerance=TOLERANCE)
    # keep one chain of duplicates (a trace in two suggestions: three photos saw it) and one more pair
    ids = [i for s in found for i in (s.a_id, s.b_id)]
    hub = next(i for i in ids if ids.count(i) >= 2)
    chain = {i for s in found if hub in (s.a_id, s.b_id) for i in (s.a_id, s.b_id)}
    pair = next({s.a_id, s.b_id} for s in found if not {s.a_id, s.b_id} & chain)
    session.push(ReplaceTraces3D(session, [t for i, t in traces.items() if i not in chain | pair], [], "keep"))
    kept = set(by_id(session.traces3d()))
    tool.suggest_action.trigger()
    qtbot.waitUntil(lambda: tool.mode == "suggest", timeout=20000)
    items = list(tool.suggestions)
    assert len(items) >= 3
    tool.accept_all_action.trigger()
    assert all(s.status for s in items) and tool.mode is None and not tool.dock.isVisible()
    after = by_id(session.project.traces3d())
    assert len(after) == len(kept) - sum(s.status == "accepted" for s in items)
    assert not chain & set(after) and not pair & set(after)  # the chain became one trace, the pair another
    assert len(after) == len(kept) - len(chain) - len(pair) + 2
    session.undo_stack.undo()
    assert set(by_id(session.project.traces3d())) == kept


def test_candidates_are_marked_and_left_to_the_user_by_accept_all(viewer, qtbot, monkeypatch):
    """A pair the rules leave apart (kind "candidate") is listed with a ?, and Accept all remaining stops
    before it: only the user accepts it."""
    session, tool = viewer.session, viewer.merge_tool
    traces = by_id(session.traces3d())
    sure, doubtful, third = suggest_merges(list(traces.values()), tolerance=TOLERANCE)[:3]
    doubtful = replace(doubtful, kind="candidate", reason="maybe")
    rival = replace(third, a_id=doubtful.a_id, kind="candidate", reason="maybe not")  # shares a trace
    monkeypatch.setattr("tracemap_gui.merge_tool.suggest_merges", lambda *a, **k: [sure, doubtful, rival])
    n = len(traces)
    tool.suggest_action.trigger()
    qtbot.waitUntil(lambda: tool.mode == "suggest", timeout=20000)
    assert tool.panel.list.item(1).text().startswith("? ")
    assert not tool.panel.list.item(0).text().startswith("?")
    items = list(tool.suggestions)
    tool.accept_all_action.trigger()
    assert [s.status for s in items] == ["accepted", "", ""]
    assert tool.mode == "suggest" and tool.index == 1 and tool.proposal is not None
    assert f"Other candidates for these pieces: {rival.a_id} + {rival.b_id}." in tool.panel.message.text()
    assert len(session.project.traces3d()) == n - 1
    tool.accept_all_action.trigger()  # nothing sure is left: the candidate stays the user's call
    assert items[1].status == "" and "accept or skip" in viewer.statusBar().currentMessage()
    key(viewer, qtbot, Qt.Key.Key_Return)
    assert items[1].status == "accepted" and len(session.project.traces3d()) == n - 2


def test_trim_between_two_clicked_vertices(viewer, qtbot):
    session, tool = viewer.session, viewer.merge_tool
    trace = longest_clickable(viewer)
    click_at(viewer, qtbot, *pickable_vertex(viewer, trace))
    assert session.selected3d == {trace.id}
    key(viewer, qtbot, Qt.Key.Key_T)
    assert tool.mode == "trim"
    n = len(trace.points)
    clicks = [display_position(viewer, trace.points[k]) for k in (n // 5, 3 * n // 4)]
    for x, y in clicks:
        click_at(viewer, qtbot, x, y)
    assert session.selected3d == {trace.id}  # the clicks marked vertices, they did not select
    assert preview_points(viewer) is not None
    key(viewer, qtbot, Qt.Key.Key_Return)

    trimmed = by_id(session.project.traces3d())[trace.id]
    lo = int(np.flatnonzero((trace.points == trimmed.points[0]).all(axis=1))[0])
    assert len(trimmed.points) < n
    np.testing.assert_array_equal(trimmed.points, trace.points[lo:lo + len(trimmed.points)])
    ends = [display_position(viewer, p) for p in trimmed.points[[0, -1]]]
    for (x, y), (cx, cy) in zip(ends, clicks):
        assert np.hypot(x - cx, y - cy) <= 1.0  # the vertex nearest each click (clicked on a vertex)
    assert trimmed.term_start == "" and trimmed.term_end == ""  # both ends were cut
    session.undo_stack.undo()
    np.testing.assert_array_equal(by_id(session.project.traces3d())[trace.id].points, trace.points)


def test_trim_one_click_keeps_a_side(viewer, qtbot):
    session, tool = viewer.session, viewer.merge_tool
    trace = longest_clickable(viewer)
    session.select3d({trace.id})
    tool.trim_action.trigger()
    click = display_position(viewer, trace.points[len(trace.points) // 2])
    click_at(viewer, qtbot, *click)
    assert len(tool.marks) == 1 and tool.keep_end_action.isEnabled()
    mark = tool.marks[0]
    x, y = display_position(viewer, trace.points[mark])
    assert np.hypot(x - click[0], y - click[1]) <= 1.0
    tool.keep_end_action.trigger()
    tool.accept_action.trigger()
    trimmed = by_id(session.project.traces3d())[trace.id]
    np.testing.assert_array_equal(trimmed.points, trace.points[mark:])
    assert trimmed.term_start == "" and trimmed.term_end == trace.term_end


def test_tolerance_and_distances_are_in_the_registered_frame(viewer, qtbot):
    session, tool = viewer.session, viewer.merge_tool
    register(session.project, 2.0)
    tool.panel.tolerance.setValue(60.0)  # mm of the registered frame: 30 mm on the mesh
    assert tool.tolerance == pytest.approx(TOLERANCE)
    tool.suggest_action.trigger()
    qtbot.waitUntil(lambda: tool.mode == "suggest", timeout=20000)
    joined = next(k for k, s in enumerate(tool.suggestions) if s.suggestion.kind != "overlap")
    item = tool.suggestions[joined]
    assert f"{2 * item.measure.gap * 1000:.0f} mm" in tool.panel.list.item(joined).text()


def test_the_list_says_how_duplicates_overlap():
    """A share for duplicates, the overlapping length for pieces overlapping end to end (their share may be
    small), and no direction for a shred too short to have one (its angle is NaN)."""
    suggestion = MergeSuggestion(3, 7, 0.5, "")
    duplicates = Overlap(0.8, 0.4, 0.004, 2.5, True, 0.0, 1.2, (0, 9), (0, 9))
    end_to_end = replace(duplicates, fraction_ab=0.2, fraction_ba=0.1, overlap_length=0.3, end_to_end=True)
    shred = replace(duplicates, fraction_ab=1.0, angle=np.nan)
    assert Suggested(suggestion, duplicates).label() == "3 + 7: 80% overlap, 4.0 mm apart, 2.5°"
    assert Suggested(suggestion, end_to_end).label(scale=2.0) == \
        "3 + 7: overlap end to end for 300 mm, 8.0 mm apart, 2.5°"
    assert Suggested(suggestion, shred).label() == "3 + 7: 100% overlap, 4.0 mm apart"


def test_duplicates_of_two_kinds_wait_for_one_kind_then_merge(viewer, qtbot):
    """A duplicate pair one of whose traces was made bedding is listed last with a ?, left alone by Accept all;
    shown, it selects the pair, and once the Kind menu gives both one kind the merge is proposed and taken."""
    from tracemap_gui.commands import SetKind

    session, tool = viewer.session, viewer.merge_tool
    traces = by_id(session.traces3d())
    first = suggest_merges(list(traces.values()), tolerance=TOLERANCE)[0]
    session.push(SetKind(session, "bedding", ids3d=[first.a_id]))
    assert by_id(session.traces3d())[first.b_id].kind == "fracture"
    tool.suggest_action.trigger()
    qtbot.waitUntil(lambda: tool.mode == "suggest", timeout=20000)
    k = next(k for k, s in enumerate(tool.suggestions) if {s.suggestion.a_id, s.suggestion.b_id} == {first.a_id,
                                                                                                      first.b_id})
    assert tool.suggestions[k].suggestion.kind == "kinds" and tool.panel.list.item(k).text().startswith("? ")
    assert all(s.suggestion.kind == "kinds" for s in tool.suggestions[k:])  # scored below every other kind
    tool.go_to(k)
    assert tool.proposal is None and session.selected3d == {first.a_id, first.b_id}
    assert "is bedding" in tool.panel.message.text() and "Kind → Make selected traces" in tool.panel.message.text()
    viewer.make_kind("bedding")
    assert tool.index == k and tool.proposal is not None  # shown again: now one kind, the merge is proposed
    key(viewer, qtbot, Qt.Key.Key_Return)
    assert tool.suggestions[k].status == "accepted"
    merged = by_id(session.project.traces3d())
    assert first.a_id not in merged and first.b_id not in merged and merged[max(merged)].kind == "bedding"
