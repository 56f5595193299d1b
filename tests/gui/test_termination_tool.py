"""Setting a termination by clicking an end node in the offscreen 3D viewer (quick demo)."""

from PySide6.QtCore import QPoint, Qt

from tests.gui.test_viewer3d import display_position, visible_trace
from tracemap_gui.termination_tool import NODE_PICK_PX


def click_display(window, qtbot, x, y):
    canvas = window.view._canvas
    qtbot.mouseClick(canvas, Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                     QPoint(x, canvas.height() - 1 - y))


def stored(window, trace_id):
    return next(t for t in window.session.project.traces3d() if t.id == trace_id)


def test_click_an_end_node_and_choose_its_code(viewer, qtbot):
    tool = viewer.termination_tool
    trace = visible_trace(viewer)
    x, y = display_position(viewer, trace.points[-1])
    click_display(viewer, qtbot, x, y)
    assert not tool.menu.isVisible()  # the tool is off: an ordinary click
    tool.action.trigger()
    trace, end = tool.node_at(x + NODE_PICK_PX // 2, y)  # nodes may be shared: the one drawn nearest
    click_display(viewer, qtbot, x + NODE_PICK_PX // 2, y)
    assert tool.menu.isVisible() and tool.target == (trace.id, end)
    assert viewer.session.selected3d == {trace.id}
    field = f"term_{end}"
    code = "X" if getattr(trace, field) == "T" else "T"
    next(a for a in tool.menu.actions() if a.data() == code).trigger()
    assert getattr(stored(viewer, trace.id), field) == code
    viewer.session.undo_stack.undo()
    assert getattr(stored(viewer, trace.id), field) == getattr(trace, field)
    viewer.session.undo_stack.redo()
    assert getattr(stored(viewer, trace.id), field) == code


def test_a_click_away_from_nodes_is_an_ordinary_selection(viewer, qtbot):
    tool = viewer.termination_tool
    tool.action.trigger()
    trace = visible_trace(viewer)
    x, y = display_position(viewer, trace.points[len(trace.points) // 2])
    if tool.node_at(x, y) is None:  # the middle of a long trace is far from every node
        click_display(viewer, qtbot, x, y)
        assert not tool.menu.isVisible() and viewer.session.selected3d == {trace.id}
    click_display(viewer, qtbot, 2, 2)
    assert not tool.menu.isVisible()
